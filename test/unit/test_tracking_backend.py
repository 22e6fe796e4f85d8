"""The tracker's back-end actor and its map snapshots: corrections come back through futures and
are committed by the front-end, failures stay inside their future, close() fails what is pending."""
from __future__ import annotations

import logging
from concurrent.futures import Future

import numpy as np
import pytest

from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.runtime.worker import WorkerStopped
from memgs_ros.core.tracking import TrackerConfig, TrackingState, make_tracker
from memgs_ros.core.tracking.backend import actor as backend_module
from memgs_ros.core.tracking.backend import ba_problem
from memgs_ros.core.tracking.backend.actor import GlobalBAOutcome, LocalBAOutcome, TrackingBackend
from memgs_ros.core.tracking.backend.ba_problem import global_problem, local_problem
from memgs_ros.core.tracking.backend.bundle_adjustment import apply_left_update, camera_shift_ratio
from memgs_ros.core.tracking.features.features import FrameFeatures
from memgs_ros.core.tracking.frontend.corrections import BackendLink
from memgs_ros.core.tracking.frontend.local_map import SparseKeyframe, SparseMap
from memgs_ros.io.synthetic import SyntheticSpec, generate_frames

K = np.array([[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]])
BF = 300.0 * 0.08
LEVELS = 1.2 ** -np.arange(8, dtype=np.float64)


def _noisy_map(n_kf: int = 6, n_pts: int = 200, seed: int = 0) -> tuple[SparseMap, np.ndarray]:
    """Keyframes 0.1 m apart all seeing the same points, poses 2 cm / 0.6 deg off but the first;
    points created by keyframe 0. Returns (map, true T_cw [N, 4, 4])."""
    rng = np.random.default_rng(seed)
    X = rng.uniform([-2.0, -1.5, 2.5], [2.0, 1.5, 5.0], (n_pts, 3))
    m = SparseMap()
    T_true = []
    for k in range(n_kf):
        T = apply_left_update(np.eye(4), np.array([0.0, 0.02 * k, 0.0, -0.1 * k, 0.0, 0.0]))
        p = X @ T[:3, :3].T + T[:3, 3]
        uv = np.column_stack([K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2], K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]])
        uv += rng.normal(0.0, 0.3, uv.shape)
        feats = FrameFeatures(uv.astype(np.float32), uv, np.zeros(n_pts, np.int64),
                              rng.integers(0, 256, (n_pts, 32), dtype=np.uint8), p[:, 2] + rng.normal(0, 0.005, n_pts))
        T_noisy = T if k == 0 else apply_left_update(T, rng.normal(0.0, 0.01, 6))
        kf = SparseKeyframe(m.new_keyframe_id(), k, T_noisy, feats, np.full(n_pts, -1, np.int64))
        m.add_keyframe(kf)
        if k == 0:
            ids = m.add_points(X + rng.normal(0.0, 0.01, X.shape), feats.desc, feats.octave, 0, np.arange(n_pts))
        else:
            m.add_observations(ids, kf.keyframe_id, np.arange(n_pts))
        T_true.append(T)
    return m, np.stack(T_true)


def _backend(threaded: bool, **cfg: object) -> TrackingBackend:
    return TrackingBackend(TrackerConfig(**cfg), K, BF, (320, 240), LEVELS, None, False, 1, threaded)  # type: ignore[arg-type]


def _gate(backend: TrackingBackend) -> Future[None]:
    """Hold the worker in a command (once it runs it) until the returned future is resolved."""
    gate: Future[None] = Future()
    entered: Future[None] = Future()

    def hold() -> None:
        entered.set_result(None)
        gate.result(timeout=30)

    backend.submit("gate", hold)
    entered.result(timeout=30)
    return gate


def _pose_err(m: SparseMap, T_true: np.ndarray) -> float:
    return max(float(np.linalg.norm(m.keyframes[k].T_cw[:3, 3] - T_true[k, :3, 3])) for k in m.keyframes)


def test_snapshot_is_an_immutable_copy_that_agrees_with_the_map() -> None:
    m, _ = _noisy_map()
    m.remove_observation(5, 2)
    snap = m.snapshot()
    for k, kf in m.keyframes.items():
        own = kf.point_ids[kf.point_ids >= 0]
        assert snap.covisible(own, 10, exclude=(k,)) == m.covisible(own, 10, exclude=k)
        np.testing.assert_array_equal(snap.kf_points(k), kf.point_ids)
    pids = np.flatnonzero(m.good(np.arange(m.n_points)))
    np.testing.assert_array_equal(snap.n_observations(pids), m.n_observations(pids))
    np.testing.assert_array_equal(snap.points_of([0, 3]), m.points_of([0, 3]))
    with pytest.raises(ValueError, match="read-only"):
        snap.points_w[0] = 0.0
    m.keyframes[1].T_cw = np.eye(4)  # the map goes on changing; the snapshot does not
    m.remove_keyframe(4)
    assert not np.allclose(snap.kf_T_cw(1), np.eye(4)) and 4 in snap


def test_local_ba_correction_arrives_through_its_future_and_the_front_end_commits_it() -> None:
    m, T_true = _noisy_map()
    backend = _backend(threaded=True)
    try:
        snap = m.snapshot()
        before = {k: kf.T_cw.copy() for k, kf in m.keyframes.items()}
        out = backend.local_ba(snap, 5).result(timeout=30)
        assert isinstance(out, LocalBAOutcome) and 5 in out.kf_ids and 0 not in out.kf_ids
        assert out.T_cw.shape == (len(out.kf_ids), 4, 4) and out.pose_epoch == m.pose_epoch
        for k, kf in m.keyframes.items():  # the back-end never touches the map
            np.testing.assert_array_equal(kf.T_cw, before[k])
        err0 = _pose_err(m, T_true)
        moved = m.commit_refinement(list(out.kf_ids), out.T_cw, out.point_ids, out.points_w, list(out.outliers),
                                    layout_version=out.layout_version, pose_epoch=out.pose_epoch)
        assert set(moved) == set(out.kf_ids)
        assert _pose_err(m, T_true) < 0.5 * err0
    finally:
        backend.close()


def test_a_local_ba_that_slides_its_new_keyframe_far_is_answered_but_not_committed() -> None:
    """``ba_max_shift_ratio``: a local BA that moves its new keyframe by more than that fraction of
    the keyframe's median point depth is refused at commit and counted; the map stays as tracked.
    With 0 the same BA is committed. Keyframe 5 is put 12 cm off (its points lie 2.5-5 m away, so
    the BA's pull back is ~0.03 of their depth)."""
    for ratio, committed in ((0.012, False), (0.0, True)):
        m, T_true = _noisy_map()
        kf = m.keyframes[5]
        kf.T_cw = apply_left_update(kf.T_cw, np.array([0.0, 0.0, 0.0, 0.12, 0.0, 0.0]))
        before = {k: k_.T_cw.copy() for k, k_ in m.keyframes.items()}
        backend = _backend(threaded=False, loop_closure=False, ba_max_shift_ratio=ratio)
        link = BackendLink(backend, backend.cfg)
        try:
            moves = link.keyframe_added(m, kf, segment_id=0)  # inline: answered and committed in the call
        finally:
            backend.close()
        if committed:
            assert len(moves) == 1 and link.ba_runs == 1 and link.ba_refused == 0
            assert np.linalg.norm(kf.T_cw[:3, 3] - T_true[5, :3, 3]) < 0.03  # pulled back
        else:
            assert moves == [] and link.ba_runs == 0 and link.ba_refused == 1
            for k, k_ in m.keyframes.items():
                np.testing.assert_array_equal(k_.T_cw, before[k])


def test_camera_shift_ratio_is_the_centre_move_over_the_median_depth() -> None:
    m, _ = _noisy_map()
    prob = local_problem(m.snapshot(), 5, 7, 1, LEVELS).problem
    c = len(prob.T_cw) - 1 if prob.fixed[0] else 0
    after = prob.T_cw.copy()
    after[c] = apply_left_update(after[c], np.array([0.0, 0.2, 0.0, 0.0, 0.0, 0.0]))  # a turn about the centre...
    after[c, :3, 3] = after[c, :3, :3] @ (prob.T_cw[c, :3, :3].T @ prob.T_cw[c, :3, 3])  # ...kept in place
    assert camera_shift_ratio(prob, after, c) == pytest.approx(0.0, abs=1e-9)
    R0, t0 = prob.T_cw[c, :3, :3], prob.T_cw[c, :3, 3]
    after = prob.T_cw.copy()
    after[c, :3, 3] = t0 - R0 @ np.array([0.05, 0.0, 0.0])  # the centre 5 cm along x
    z = prob.points_w[prob.obs_point[prob.obs_cam == c]] @ R0[2] + t0[2]
    assert camera_shift_ratio(prob, after, c) == pytest.approx(0.05 / np.median(z))


def test_the_link_commits_results_at_poll_and_drops_stale_ones() -> None:
    m, _ = _noisy_map()
    backend = _backend(threaded=True, loop_closure=False)
    link = BackendLink(backend, backend.cfg)
    try:
        gate = _gate(backend)
        assert link.keyframe_added(m, m.keyframes[5], segment_id=0) == []
        assert link.poll(m, 0) == [] and link.ba_runs == 0  # not answered yet: nothing moved
        gate.set_result(None)
        moves = link.wait(m, 0, frozenset({"local_ba"}), timeout_s=30)
        assert len(moves) == 1 and not moves[0].loop and link.ba_runs == 1
        assert {k for k, _ in link.refined} == set(moves[0].moved)
        # A result computed before a loop correction moved the map is stale: dropped.
        gate = _gate(backend)
        link.keyframe_added(m, m.keyframes[5], segment_id=0)
        m.apply_loop_correction(np.array([0]), np.eye(4)[None], np.eye(4), newer_than=10)
        gate.set_result(None)
        assert link.wait(m, 0, frozenset({"local_ba"}), timeout_s=30) == [] and link.ba_runs == 1
        # So is one for an earlier map segment.
        link.keyframe_added(m, m.keyframes[5], segment_id=0)
        assert link.wait(m, 1, frozenset({"local_ba"}), timeout_s=30) == [] and link.ba_runs == 1
    finally:
        link.close()


def test_a_newer_local_ba_supersedes_a_queued_one() -> None:
    m, _ = _noisy_map()
    backend = _backend(threaded=True)
    try:
        gate = _gate(backend)
        first = backend.local_ba(m.snapshot(), 4)
        second = backend.local_ba(m.snapshot(), 5)
        assert first.done() and first.result() is None  # superseded while queued
        gate.set_result(None)
        assert isinstance(second.result(timeout=30), LocalBAOutcome)
    finally:
        backend.close()


def test_global_ba_runs_between_other_requests() -> None:
    m, _ = _noisy_map(n_kf=8)
    backend = _backend(threaded=True, loop_global_ba_iterations=50, loop_global_ba_budget_s=30.0)
    try:
        order: list[str] = []
        gate = _gate(backend)
        gba = backend.global_ba(m.snapshot())
        local = backend.local_ba(m.snapshot(), 7)
        gba.add_done_callback(lambda _: order.append("global"))
        local.add_done_callback(lambda _: order.append("local"))
        gate.set_result(None)
        out = gba.result(timeout=60)
        local.result(timeout=60)
        assert order == ["local", "global"]  # the local BA did not wait for the whole global BA
        assert isinstance(out, GlobalBAOutcome) and out.correction is not None and out.correction.is_global_ba
        np.testing.assert_allclose(out.correction.T_wc_new[0], np.linalg.inv(m.keyframes[0].T_cw), atol=1e-12)
    finally:
        backend.close()


def test_inline_backend_answers_inside_the_call() -> None:
    m, _ = _noisy_map()
    backend = _backend(threaded=False)
    f = backend.local_ba(m.snapshot(), 5)
    g = backend.global_ba(m.snapshot())
    assert f.done() and isinstance(f.result(), LocalBAOutcome)
    assert g.done() and g.result().correction is not None
    assert backend.alive
    backend.close()
    assert not backend.alive
    with pytest.raises(WorkerStopped):
        backend.local_ba(m.snapshot(), 5)


def test_close_fails_pending_futures() -> None:
    m, _ = _noisy_map()
    backend = _backend(threaded=True)
    gate = _gate(backend)
    local = backend.local_ba(m.snapshot(), 5)
    gba = backend.global_ba(m.snapshot())
    assert not backend.close(timeout_s=0.2)  # the worker is still held by the gate
    for f in (local, gba):
        with pytest.raises(WorkerStopped):
            f.result(timeout=5)
    with pytest.raises(WorkerStopped):
        backend.local_ba(m.snapshot(), 5)
    gate.set_result(None)
    assert backend.close()


def test_a_failing_local_ba_does_not_stop_tracking(monkeypatch: pytest.MonkeyPatch,
                                                   caplog: pytest.LogCaptureFixture) -> None:
    def broken(*_: object, **__: object) -> None:
        raise RuntimeError("singular system")

    monkeypatch.setattr(backend_module, "local_bundle_adjustment", broken)
    spec = SyntheticSpec(width=320, height=240, n_frames=30, seed=0, supersample=1)
    frames: list[Frame] = list(generate_frames(spec))
    tracker = make_tracker(TrackerConfig(), frames[0].camera)
    try:
        with caplog.at_level(logging.WARNING, logger="memgs_ros.core.tracking.frontend.corrections"):
            results = [tracker.track(f) for f in frames]
            tracker.wait_for_ba()
            tracker.wait_for_loop_closing()
        assert all(r.state == TrackingState.OK for r in results)
        assert sum(r.keyframe is not None for r in results) >= 3
        assert tracker.backend.alive and tracker.ba_runs == 0 and tracker.poll_refined_keyframes() == []
        assert tracker.loop_stats.keyframes_indexed >= 3  # place recognition went on
        assert "local_ba failed: RuntimeError: singular system" in caplog.text
    finally:
        tracker.close()


def test_local_window_fixes_outside_keyframes_else_its_oldest() -> None:
    m, _ = _noisy_map(n_kf=6)
    snap = m.snapshot()
    sp = local_problem(snap, 5, window=3, n_fixed=1, inv_sigma_levels=LEVELS)
    assert sp is not None and sp.cams[0] == 5 and len(sp.cams) == 6  # 3 free + 3 outside, fixed
    assert sp.problem.fixed.tolist() == [False] * 3 + [True] * 3
    alone = local_problem(snap, 5, window=6, n_fixed=2, inv_sigma_levels=LEVELS)
    assert alone is not None and sorted(np.array(alone.cams)[alone.problem.fixed].tolist()) == [0, 1]
    # Every observation of the window's points by the problem's keyframes, point by point.
    assert len(sp.problem.obs_cam) == len(sp.point_ids) * len(sp.cams)
    assert np.all(np.diff(sp.problem.obs_point) >= 0)
    assert local_problem(snap, 99, window=3, n_fixed=1, inv_sigma_levels=LEVELS) is None  # gone


def test_global_problem_spreads_a_capped_point_over_its_keyframes(monkeypatch: pytest.MonkeyPatch) -> None:
    m, _ = _noisy_map(n_kf=10, n_pts=50)
    monkeypatch.setattr(ba_problem, "_GLOBAL_BA_MAX_PAIRS", 50 * 4 * 4)
    sp = global_problem(m.snapshot(), LEVELS)
    assert sp is not None and sp.problem.fixed.tolist() == [True] + [False] * 9
    per_point = np.bincount(sp.problem.obs_point)
    assert per_point.max() == 4 and per_point.min() == 4
    seen = sp.obs_kf[sp.problem.obs_point == 0].tolist()
    assert seen == [0, 3, 6, 9]  # evenly spread, first and last keyframe kept
