"""MappingSession: the one owner of the live map, driven by commands from several threads."""
from __future__ import annotations

import threading
import time
from dataclasses import replace

import numpy as np
import pytest
import torch
from frame_seeds import grid_seeds

from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.geometry.poses import quat_wxyz_to_rotmat_torch
from memgs_ros.core.mapper_service.session import MappingSession, SessionError
from memgs_ros.core.mapping.keyframes import KeyframeInput
from memgs_ros.core.mapping.mapper import MappingConfig
from memgs_ros.io.synthetic import SyntheticSpec, generate_frames


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return list(generate_frames(SyntheticSpec(width=64, height=48, n_frames=30, seed=1)))[::5]


def _cfg(**overrides: object) -> MappingConfig:
    return MappingConfig(**{"min_keyframes": 2, "pyramid_uses_per_level": 2, "merge_enabled": False,
                            "densify_start_iter": 10_000, **overrides})


def _kf(f: Frame, stamp: int, step: int = 8) -> KeyframeInput:
    p, c = grid_seeds(f, step)
    return KeyframeInput(stamp, f.T_wc_gt, f.rgb, f.depth_m, f.camera, p, c)


def _consistent(ck) -> None:  # noqa: ANN001 - MapperCheckpoint
    """A captured state is whole: each keyframe it holds is in its stamp table under its own id,
    and every per-Gaussian array has one row per Gaussian."""
    table = {int(s): k for s, k in ck.extra["keyframe_stamps"].items()}
    for kf in ck.keyframes:
        assert table.get(kf.stamp_ns) == kf.kf_id, f"keyframe {kf.kf_id} ({kf.stamp_ns}) missing from its table"
    assert sorted(table.values()) == list(range(len(table)))
    n = len(ck.gaussians)
    assert ck.keyframe_ids.shape == (n,) and ck.created_iter.shape == (n,)
    assert set(np.unique(ck.keyframe_ids)) <= set(table.values())


def test_commands_from_many_threads_leave_map_and_keyframes_consistent(frames: list[Frame]) -> None:
    """Stress: inserts, pose updates, deltas, renders and state captures from five threads for
    a few seconds while the worker trains. Also the regression test for the old mapper node's
    race, where a checkpoint's keyframe-stamp table was copied outside the map's lock while the
    insert thread wrote it (a keyframe without its stamp, or 'dictionary changed size')."""
    s = MappingSession(_cfg(), insert_queue=1000)
    errors: list[BaseException] = []
    captures: list = []
    stop = threading.Event()
    inserted: list[int] = []

    def guard(fn):  # noqa: ANN001, ANN202
        def run() -> None:
            try:
                fn()
            except BaseException as err:  # noqa: BLE001 - reported to the test thread
                errors.append(err)
        return threading.Thread(target=run)

    def insert() -> None:
        for i in range(24):
            stamp = 1_000 + i
            s.insert_keyframe(_kf(frames[i % len(frames)], stamp))
            inserted.append(stamp)
            time.sleep(0.05)

    def poses() -> None:
        rng = np.random.default_rng(0)
        while not stop.is_set():
            if inserted:
                stamp = inserted[int(rng.integers(len(inserted)))]
                T = frames[0].T_wc_gt.copy()
                T[:3, 3] += rng.normal(0, 0.01, 3)
                s.update_poses({stamp: T, 99: T})  # 99: a stamp never inserted, ignored
            time.sleep(0.01)

    def outputs() -> None:
        while not stop.is_set():
            s.delta(500).result(30)
            s.snapshot().result(30)
            s.render(frames[1].T_wc_gt).result(30)

    def capture() -> None:
        while not stop.is_set():
            captures.append(s.state_dict().result(30))

    threads = [guard(insert), guard(poses), guard(outputs), guard(capture), guard(outputs)]
    for t in threads:
        t.start()
    threads[0].join(60)
    deadline = time.monotonic() + 60  # the commands keep coming until training has stepped
    while s.status.iteration == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    stop.set()
    for t in threads[1:]:
        t.join(60)
    final = s.state_dict().result(30)
    st = s.status
    s.close()
    assert not errors, errors
    assert s.poll_events() == []
    assert len(captures) >= 3 and st.iteration > 0
    for ck in captures + [final]:
        _consistent(ck)
    assert len(final.keyframes) == 24 and st.keyframes == 24 and st.counters["keyframes"] == 24
    assert st.counters["keyframe_pose_updates"] > 0
    assert st.gaussians == len(final.gaussians) > 0


def test_lockstep_is_train_then_acknowledge_and_deterministic(frames: list[Frame]) -> None:
    snaps = []
    for _ in range(2):
        s = MappingSession(_cfg(), free_running=False)
        for i, f in enumerate(frames[:3]):
            s.insert_keyframe(_kf(f, 10 + i))
            st = s.train(4).result(60)  # FIFO: trains after the insertion above
        assert st is not None and s.status.iteration == 8  # nothing before ready (2 keyframes)
        for _ in range(20):  # the worker idles between these round trips: a free-running one trains there
            s.delta(0).result(30)
        assert s.status.iteration == 8  # a lockstep worker never trains on its own
        snaps.append(s.snapshot().result(30))
        s.close()
    assert np.array_equal(snaps[0].ids, snaps[1].ids) and np.array_equal(snaps[0].xyz, snaps[1].xyz)


def test_full_insert_queue_drops_the_oldest_whole_and_counts_it(frames: list[Frame]) -> None:
    s = MappingSession(_cfg(min_keyframes=100, live_min_keyframes=100), insert_queue=1)
    gate = threading.Event()
    busy = s.call(lambda _m: gate.wait(30))  # the worker is held: insertions wait in the queue
    futures = [s.insert_keyframe(_kf(frames[i], 100 + i)) for i in range(3)]
    assert futures[0].result(5) is None and futures[1].result(5) is None  # dropped, resolved at once
    assert s.status.insert_queue == 1
    gate.set()
    assert busy.result(30) is True and futures[2].result(30) > 0
    events = s.poll_events()
    assert [e.kind for e in events] == ["keyframe_overload"] * 2
    assert s.status.keyframes == 1
    assert s.state_dict().result(30).extra["keyframe_stamps"] == {"102": 0}
    s.close()


def test_rigid_correction_moves_a_keyframe_and_its_gaussians(frames: list[Frame]) -> None:
    s = MappingSession(_cfg(), free_running=False)
    for i, f in enumerate(frames[:3]):
        s.insert_keyframe(_kf(f, 10 + i))

    def rows(m):  # noqa: ANN001, ANN202
        g = m.gmap
        return (g.keyframe_ids.clone(), g.means.detach().clone(), g.quats_wxyz.detach().clone())

    kf_ids, means0, quats0 = s.call(rows).result(30)
    c, sn = np.cos(0.2), np.sin(0.2)
    D = np.eye(4)
    D[:3, :3] = [[c, -sn, 0], [sn, c, 0], [0, 0, 1]]
    D[:3, 3] = [0.1, -0.2, 0.05]
    T_new = D @ frames[1].T_wc_gt
    T_shift = frames[2].T_wc_gt.copy()
    T_shift[:3, 3] += [0.0, 0.3, 0.0]  # keyframe 2: a pure translation, in the same command
    n_moved = int(((kf_ids == 1) | (kf_ids == 2)).sum())
    assert s.correct_keyframes({11: T_new, 12: T_shift, 12345: T_new}).result(30) == (2, n_moved)
    _, means1, quats1 = s.call(rows).result(30)
    moved = kf_ids == 1
    Dt = torch.as_tensor(D, dtype=torch.float32)
    torch.testing.assert_close(means1[moved], means0[moved] @ Dt[:3, :3].T + Dt[:3, 3], atol=1e-5, rtol=0)
    torch.testing.assert_close(quat_wxyz_to_rotmat_torch(quats1[moved]),
                               Dt[:3, :3] @ quat_wxyz_to_rotmat_torch(quats0[moved]), atol=1e-5, rtol=0)
    shifted = kf_ids == 2
    torch.testing.assert_close(means1[shifted], means0[shifted] + torch.tensor([0.0, 0.3, 0.0]), atol=1e-5, rtol=0)
    torch.testing.assert_close(quats1[shifted], quats0[shifted], atol=1e-6, rtol=0)
    assert torch.equal(means1[kf_ids == 0], means0[kf_ids == 0])
    kfs = {k.kf_id: k for k in s.state_dict().result(30).keyframes}
    np.testing.assert_allclose(kfs[1].T_wc, T_new)
    np.testing.assert_allclose(kfs[0].T_wc, frames[0].T_wc_gt)
    s.close()


def test_bad_keyframe_is_an_event_and_finish_refuses_later_ones(frames: list[Frame]) -> None:
    s = MappingSession(_cfg(), free_running=False)
    f = frames[0]
    bad = KeyframeInput(1, f.T_wc_gt, f.rgb[:, :10], f.depth_m, f.camera, np.zeros((0, 3)), np.zeros((0, 3)))
    assert s.insert_keyframe(bad).result(30) is None
    assert [e.kind for e in s.poll_events()] == ["bad_keyframe"] and s.status.keyframes == 0
    assert s.insert_keyframe(_kf(f, 2)).result(30) > 0
    done = s.finish(5).result(30)
    # One keyframe of the two training waits for: the run has ended, so the final iterations
    # train on it (a live run that tracked few frames at 2x left its map untrained, 12 dB).
    assert done.final_iterations == 5 and s.status.iteration == 5
    assert s.insert_keyframe(_kf(frames[1], 3)).result(30) is None and s.status.finished
    s.close()
    with pytest.raises(SessionError):
        s.train(1)


def test_an_interrupted_finish_stops_after_its_step_and_the_state_is_saved_next(frames: list[Frame]) -> None:
    """A node shutting down mid-finish (its runner died) must save within its stop deadline: the
    interrupt ends the final iterations after the step in progress, and the save queued behind
    them runs at once."""
    s = MappingSession(_cfg(), free_running=False)
    for i, f in enumerate(frames[:2]):
        s.insert_keyframe(_kf(f, 20 + i))
    finishing = s.finish(1_000_000)  # far more than the test could wait for
    deadline = time.monotonic() + 60
    while s.status.iterations_final < 3:  # the finish is under way
        assert time.monotonic() < deadline, "the finish did not start"
        time.sleep(0.01)
    saved = s.state_dict()
    s.interrupt()
    done = finishing.result(60)
    assert 3 <= done.final_iterations < 1_000_000
    assert saved.result(60).iteration == s.status.iteration == done.final_iterations
    s.close()


def test_state_round_trip_through_a_new_session(frames: list[Frame]) -> None:
    s = MappingSession(_cfg(), free_running=False)
    for i, f in enumerate(frames[:3]):
        s.insert_keyframe(_kf(f, 10 + i))
    s.train(5).result(60)
    ck = s.state_dict().result(30)
    assert s.state_dict(only_if_changed=True).result(30) is None
    s.close()
    r = MappingSession(_cfg(), free_running=False, checkpoint=ck)
    assert r.resumed_stamps == {10, 11, 12} and r.status.iteration == 5
    assert r.insert_keyframe(_kf(frames[0], 11)).result(30) is None  # a stamp it holds already
    assert r.insert_keyframe(_kf(frames[3], 13)).result(30) > 0
    assert r.state_dict().result(30).extra["keyframe_stamps"]["13"] == 3
    r.close()


def test_bundle_adjustment_and_loop_poses_take_separate_paths(frames: list[Frame]) -> None:
    """Bundle adjustment's refined poses only replace the training pose, however large; a loop
    correction moves the keyframe's Gaussians with it (memgs/keyframe/refined_poses vs
    memgs/keyframe/loop_corrected_poses)."""
    s = MappingSession(_cfg(), free_running=False)
    for i, f in enumerate(frames[:3]):
        s.insert_keyframe(_kf(f, 10 + i))
    rows = lambda m: (m.gmap.keyframe_ids.clone(), m.gmap.means.detach().clone())  # noqa: E731
    kf_ids, means0 = s.call(rows).result(30)
    T_loop = frames[1].T_wc_gt.copy()
    T_loop[:3, 3] += [0.2, 0.0, 0.0]  # 20 cm: a loop correction
    T_ba = frames[2].T_wc_gt.copy()
    T_ba[:3, 3] += [0.03, 0.0, 0.0]  # 3 cm from bundle adjustment: still only the training pose
    assert s.update_poses({12: T_ba}).result(30) == 1
    assert s.correct_keyframes({11: T_loop}).result(30) == (1, int((kf_ids == 1).sum()))
    _, means1 = s.call(rows).result(30)
    torch.testing.assert_close(means1[kf_ids == 1], means0[kf_ids == 1] + torch.tensor([0.2, 0.0, 0.0]),
                               atol=1e-5, rtol=0)
    assert torch.equal(means1[kf_ids != 1], means0[kf_ids != 1])
    kfs = {k.kf_id: k for k in s.state_dict().result(30).keyframes}
    np.testing.assert_allclose(kfs[2].T_wc, T_ba)
    assert s.status.counters["keyframes_corrected"] == 1
    s.close()


@pytest.mark.parametrize("densify", [True, False])
def test_final_iterations_densify_only_when_asked(frames: list[Frame], densify: bool) -> None:
    """finish(n, densify=False) polishes the map without growing it; densify=True densifies as
    training does (every interval from densify_start_iter)."""
    s = MappingSession(_cfg(densify_start_iter=5, densify_interval=5, densify_grad_threshold=0.0), free_running=False)
    for i, f in enumerate(frames[:3]):
        s.insert_keyframe(_kf(f, 10 + i))
    s.train(3).result(60)
    before = s.status.gaussians
    done = s.finish(20, densify=densify).result(120)
    assert done.final_iterations == 20
    assert (done.gaussians > before) == densify, (before, done.gaussians)
    s.close()


def test_densification_follows_new_keyframes_in_flight(frames: list[Frame]) -> None:
    """In flight the map densifies only within densify_window_iters of the newest keyframe: a flight
    over a room already mapped brings no keyframe and the map stops growing with the training time;
    the next keyframe opens the window again."""
    s = MappingSession(_cfg(densify_start_iter=5, densify_interval=5, densify_grad_threshold=0.0,
                            densify_window_iters=10, prune_opacity=0.0), free_running=False)
    size = lambda m: len(m.gmap)  # noqa: E731
    for i, f in enumerate(frames[:3]):
        s.insert_keyframe(_kf(f, 10 + i))
    seeded = s.call(size).result(30)
    s.train(10).result(60)  # densifies at 5 and 10
    opened = s.call(size).result(30)
    assert opened > seeded
    s.train(20).result(60)  # iterations 11-30: the window closed at 10
    assert s.call(size).result(30) == opened
    s.insert_keyframe(_kf(frames[3], 13))
    with_seeds = s.call(size).result(30)
    s.train(10).result(60)  # densifies at 35 and 40
    assert s.call(size).result(30) > with_seeds
    s.close()


def test_final_budget_ends_the_final_iterations_early(frames: list[Frame]) -> None:
    """finish(n, budget_s=b) stops once the final iterations have taken b seconds (checked after
    each: at least one runs); a budget they fit in changes nothing."""
    s = MappingSession(_cfg(), free_running=False)
    for i, f in enumerate(frames[:2]):
        s.insert_keyframe(_kf(f, 10 + i))
    done = s.finish(50, budget_s=1e-6).result(120)
    assert done.final_iterations == 1 and s.status.iteration == 1
    s.close()
    s = MappingSession(_cfg(), free_running=False)
    for i, f in enumerate(frames[:2]):
        s.insert_keyframe(_kf(f, 10 + i))
    assert s.finish(4, budget_s=1e6).result(120).final_iterations == 4
    s.close()


def test_live_training_starts_at_the_first_keyframe_and_times_each_keyframe(frames: list[Frame]) -> None:
    """Free-running, the worker trains from live_min_keyframes (1) keyframes, not min_keyframes;
    each keyframe's intake CPU and its latency from the tracker's decision to its first training
    step are in the status; finish counts its own iterations apart."""
    s = MappingSession(_cfg(min_keyframes=50))
    try:
        decided = time.time_ns()
        s.insert_keyframe(_kf(frames[0], 100), received_cpu_s=0.002).result(30)
        end = time.monotonic() + 30
        while s.status.iteration < 3 and time.monotonic() < end:
            time.sleep(0.01)
        st = s.status
        assert st.iteration >= 3 and st.keyframes == 1  # 1 of min_keyframes=50: live does not wait
        s.insert_keyframe(replace(_kf(frames[1], 200), decided_ns=decided)).result(30)
        while s.status.keyframe_timing.used < 2 and time.monotonic() < end:
            time.sleep(0.01)
        t = s.status.keyframe_timing
        assert t.used == 2 and t.waiting == 0
        assert t.intake_ms_p95 is not None and t.intake_ms_p95 >= 2.0  # the caller's 2 ms counted
        assert t.latency_ms_median is not None and 0.0 < t.latency_ms_median < 30_000.0
        done = s.finish(7).result(60)
        assert done.final_iterations == 7 and s.status.iterations_final == 7
        gauges = s.status.gauges()
        assert gauges["keyframes_used"] == 2 and "keyframe_latency_ms_p95" in gauges
    finally:
        s.close()


def test_lockstep_waits_for_min_keyframes_whatever_live_would_do(frames: list[Frame]) -> None:
    s = MappingSession(_cfg(min_keyframes=2, live_min_keyframes=1), free_running=False)
    try:
        s.insert_keyframe(_kf(frames[0], 100)).result(30)
        assert s.train(3).result(30) is None and s.status.iteration == 0
        s.insert_keyframe(_kf(frames[1], 200)).result(30)
        assert s.train(3).result(30) is not None and s.status.iteration == 3
    finally:
        s.close()


def test_keyframe_timings_count_the_first_draw_only() -> None:
    from memgs_ros.core.mapper_service.keyframe_timing import KeyframeTimings

    t = KeyframeTimings()
    t.inserted(0, 1_000_000_000, 5.0)
    t.inserted(1, 0, 15.0)  # decision time unknown: no latency
    t.trained(0, now_ns=1_050_000_000)
    t.trained(0, now_ns=9_000_000_000)  # a later draw of the same keyframe is no new latency
    t.trained(7)  # not inserted here (resumed from a checkpoint)
    s = t.summary()
    assert (s.used, s.waiting) == (1, 1)
    assert s.latency_ms_median == 50.0 and s.intake_ms_median == 10.0 and s.intake_ms_p95 == 14.5
    t.trained(1)
    assert (t.summary().used, t.summary().waiting, t.summary().latency_ms_median) == (2, 0, 50.0)


def test_the_work_that_set_the_device_peak_is_named() -> None:
    """PeakAttribution keeps, per kind of work, the highest peak it raised the allocator to (read
    from the device; here a stand-in counter, as a CPU has no allocator statistics)."""
    from memgs_ros.core.mapping.device_peaks import PeakAttribution

    peak = [100]
    p = PeakAttribution(torch.device("cpu"), read_peak=lambda: peak[0])
    with p.work("forward"):
        peak[0] = 300
    with p.work("merge"):
        peak[0] = 900
    with p.work("forward"):
        pass  # below the peak: nothing to attribute
    with p.work("backward"):
        peak[0] = 950
    assert p.by_work == {"forward": 300, "merge": 900, "backward": 950} and p.peak_setter() == "backward"
    assert not PeakAttribution(torch.device("cpu")).enabled  # no allocator statistics on a CPU


def test_final_iterations_go_on_to_a_total_when_little_was_trained(frames: list[Frame]) -> None:
    """finish(total_iterations=N): at least final_iterations, and more while the map has trained
    fewer than N in all (a live mapper on a slow machine); a map past N gets final_iterations."""
    s = MappingSession(_cfg(min_keyframes=1), free_running=False)
    try:
        s.insert_keyframe(_kf(frames[0], 100)).result(30)
        s.train(5).result(30)
        done = s.finish(3, total_iterations=20).result(60)
        assert done.final_iterations == 15 and s.status.iteration == 20
    finally:
        s.close()
    s = MappingSession(_cfg(min_keyframes=1), free_running=False)
    try:
        s.insert_keyframe(_kf(frames[0], 100)).result(30)
        s.train(25).result(30)
        assert s.finish(3, total_iterations=20).result(60).final_iterations == 3
    finally:
        s.close()


def test_paused_training_holds_the_iteration_and_resumes(frames: list[Frame]) -> None:
    """set_training(False) (a managed mapper's deactivate) stops the free-running steps between
    commands; keyframes are still taken in; set_training(True) goes on from there."""
    s = MappingSession(_cfg())
    try:
        s.insert_keyframe(_kf(frames[0], 100)).result(30)
        end = time.monotonic() + 30
        while s.status.iteration < 2 and time.monotonic() < end:
            time.sleep(0.01)
        assert s.set_training(False).result(30) is False
        held = s.status.iteration
        s.insert_keyframe(_kf(frames[1], 200)).result(30)  # taken in while paused
        time.sleep(0.3)  # a window in which a running session steps many times (~50 ms a step here)
        assert s.status.iteration == held and s.status.keyframes == 2
        assert s.set_training(True).result(30) is True
        while s.status.iteration <= held and time.monotonic() < end:
            time.sleep(0.01)
        assert s.status.iteration > held
    finally:
        s.close()


@pytest.mark.parametrize("units", ["metres", "millimetres"])
def test_each_keyframe_image_is_prepared_once(frames: list[Frame], units: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """A keyframe's colour and depth are undistorted, resized and turned into metres once in the
    mapper's process (one ``ViewPreparation`` call each), whatever trains on them afterwards and
    in whichever of REP-118's units the depth came (32FC1 metres, 16UC1 millimetres)."""
    from memgs_ros.core.geometry.view import ViewPreparation

    calls: list[int] = []
    real = ViewPreparation.__call__

    def counting(self, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        calls.append(1)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(ViewPreparation, "__call__", counting)
    s = MappingSession(_cfg(), free_running=False)
    try:
        for i, f in enumerate(frames[:4]):
            kf = _kf(f, 10 + i)
            if units == "millimetres":
                mm = np.where(np.isfinite(kf.depth), np.rint(kf.depth * 1000.0), 0).astype(np.uint16)
                kf = replace(kf, depth=mm, depth_scale=1000.0)
            s.insert_keyframe(kf)
            s.train(6).result(60)
        s.snapshot().result(30)
        assert s.status.keyframes == 4 and s.status.iteration > 0
    finally:
        s.close()
    assert len(calls) == 4
