"""Association, Umeyama alignment and ATE against hand-computed values."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from memgs_ros.core.metrics.trajectory import align_rotations, align_umeyama, associate, ate, path_length_m, rpe
from memgs_ros.errors import DataError

MS = 1_000_000


def _rigid(rotvec: tuple[float, float, float], t: tuple[float, float, float]) -> np.ndarray:
    G = np.eye(4)
    G[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    G[:3, 3] = t
    return G


def _poses(positions: np.ndarray, rotvecs: np.ndarray | None = None) -> np.ndarray:
    T = np.tile(np.eye(4), (len(positions), 1, 1))
    T[:, :3, 3] = positions
    if rotvecs is not None:
        T[:, :3, :3] = Rotation.from_rotvec(rotvecs).as_matrix()
    return T


def test_associate_nearest_with_jitter() -> None:
    gt = np.arange(0, 1000 * MS, 10 * MS)  # 100 Hz
    rng = np.random.default_rng(0)
    est = np.arange(5 * MS, 900 * MS, 33 * MS) + rng.integers(-3 * MS, 3 * MS, 28)
    ia, ib = associate(est, gt, 20 * MS)
    assert np.array_equal(ia, np.arange(est.size))
    expected = np.argmin(np.abs(est[:, None] - gt[None, :]), axis=1)
    assert np.array_equal(ib, expected)


def test_associate_is_one_to_one_and_respects_max_dt() -> None:
    a = np.array([100, 104, 300, 1000]) * MS
    b = np.array([103, 310]) * MS
    ia, ib = associate(a, b, 20 * MS)
    # 104 is nearer to 103 than 100 is; 100 then has nothing left; 1000 is too far.
    assert ia.tolist() == [1, 2]
    assert ib.tolist() == [0, 1]
    ia, ib = associate(a, b, 5 * MS)
    assert ia.tolist() == [1] and ib.tolist() == [0]
    ia, ib = associate(a, np.zeros(0, dtype=np.int64), 5 * MS)
    assert ia.size == 0 and ib.size == 0


def test_associate_unsorted_inputs() -> None:
    a = np.array([300, 100, 200]) * MS
    b = np.array([201, 99, 305]) * MS
    ia, ib = associate(a, b, 10 * MS)
    assert ia.tolist() == [0, 1, 2]
    assert ib.tolist() == [2, 1, 0]


def test_umeyama_recovers_se3_exactly() -> None:
    rng = np.random.default_rng(1)
    p = rng.normal(size=(20, 3))
    G = _rigid((0.3, -1.2, 2.0), (1.0, -2.0, 0.5))
    q = p @ G[:3, :3].T + G[:3, 3]
    al = align_umeyama(p, q, with_scale=False)
    assert np.allclose(al.R, G[:3, :3], atol=1e-12)
    assert np.allclose(al.t, G[:3, 3], atol=1e-12)
    assert al.s == 1.0
    assert np.allclose(al.apply(p), q, atol=1e-12)


def test_umeyama_recovers_sim3_scale() -> None:
    rng = np.random.default_rng(2)
    p = rng.normal(size=(15, 3))
    G = _rigid((-0.7, 0.1, 0.4), (0.0, 3.0, -1.0))
    q = 2.5 * p @ G[:3, :3].T + G[:3, 3]
    al = align_umeyama(p, q, with_scale=True)
    assert al.s == pytest.approx(2.5, abs=1e-12)
    assert np.allclose(al.R, G[:3, :3], atol=1e-12)
    assert np.allclose(al.t, G[:3, 3], atol=1e-12)
    assert np.allclose(al.as_matrix()[:3, :3], 2.5 * G[:3, :3], atol=1e-12)


def test_umeyama_planar_points_give_a_rotation_not_a_reflection() -> None:
    rng = np.random.default_rng(3)
    p = np.c_[rng.normal(size=(10, 2)), np.zeros(10)]
    G = _rigid((0.2, 0.5, -0.3), (0.1, 0.2, 0.3))
    q = p @ G[:3, :3].T + G[:3, 3]
    al = align_umeyama(p, q)
    assert np.linalg.det(al.R) == pytest.approx(1.0)
    assert np.allclose(al.R, G[:3, :3], atol=1e-10)
    # A mirrored target cannot be matched by a rotation: the result must still be proper.
    x = rng.normal(size=(10, 3))
    mirrored = x * [1.0, 1.0, -1.0]
    U, _, Vt = np.linalg.svd((mirrored - mirrored.mean(0)).T @ (x - x.mean(0)))
    assert np.linalg.det(U @ Vt) < 0  # the unconstrained SVD answer is a reflection here
    al_m = align_umeyama(x, mirrored)
    assert np.linalg.det(al_m.R) == pytest.approx(1.0)


def test_umeyama_needs_three_points() -> None:
    with pytest.raises(DataError, match="at least 3 point pairs, got 2"):
        align_umeyama(np.zeros((2, 3)), np.zeros((2, 3)))


def _hand_case() -> tuple[np.ndarray, np.ndarray, float]:
    """Ground truth on the six unit axis points; perturbations with zero sum and zero
    cross-covariance with the points, so the optimal alignment is the identity and the
    errors are the perturbation lengths: 3, 3, 4, 4, 5, 5 cm."""
    gt_p = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    dx, dy, dz = np.array([0, 0.03, 0]), np.array([0, 0, 0.04]), np.array([0, -0.03, -0.04])
    est_p = gt_p + np.array([dx, dx, dy, dy, dz, dz])
    rmse = float(np.sqrt((2 * 0.03 ** 2 + 2 * 0.04 ** 2 + 2 * 0.05 ** 2) / 6))
    return gt_p, est_p, rmse


def test_ate_of_perturbed_trajectory_matches_hand_computation() -> None:
    gt_p, est_p, rmse = _hand_case()
    gt_stamps = np.arange(6) * 100 * MS
    est_stamps = gt_stamps + np.array([3, -2, 1, 0, -4, 2]) * MS  # jitter, within 0.1 s
    G = _rigid((0.4, 0.0, -0.9), (5.0, -1.0, 2.0))  # the estimate lives in another world frame
    est_T = np.einsum("ij,njk->nik", G, _poses(est_p))
    res = ate(est_stamps, est_T, gt_stamps, _poses(gt_p))
    assert res.n_matched == 6
    assert res.rmse_m == pytest.approx(rmse, abs=1e-12)
    assert res.mean_m == pytest.approx((0.03 + 0.04 + 0.05) / 3, abs=1e-12)
    assert res.median_m == pytest.approx(0.04, abs=1e-12)
    assert res.max_m == pytest.approx(0.05, abs=1e-12)
    assert np.allclose(np.sort(res.errors_m), [0.03, 0.03, 0.04, 0.04, 0.05, 0.05], atol=1e-12)
    assert np.allclose(res.alignment.as_matrix(), np.linalg.inv(G), atol=1e-12)
    assert res.rotation_rmse_deg == pytest.approx(0.0, abs=1e-6)
    assert res.to_dict()["n_matched"] == 6


def test_ate_sim3_removes_scale_and_rotation_error_is_reported() -> None:
    rng = np.random.default_rng(4)
    gt_p = rng.normal(size=(30, 3))
    rv = rng.normal(size=(30, 3)) * 0.3
    gt_T = _poses(gt_p, rv)
    stamps = np.arange(30) * 33 * MS
    # Estimate: world rotated and scaled by 0.5, every camera also turned by 2 degrees about an
    # axis of its own.
    G = _rigid((0.0, 0.5, 0.0), (1.0, 1.0, 1.0))
    est_T = np.einsum("ij,njk->nik", G, gt_T)
    est_T[:, :3, 3] *= 0.5
    axes = rng.normal(size=(30, 3))
    noise = Rotation.from_rotvec(axes / np.linalg.norm(axes, axis=1, keepdims=True) * np.radians(2.0))
    est_T[:, :3, :3] = est_T[:, :3, :3] @ noise.as_matrix()
    res = ate(stamps, est_T, stamps, gt_T, sim3=True)
    assert res.rmse_m == pytest.approx(0.0, abs=1e-9)
    assert res.alignment.s == pytest.approx(2.0, abs=1e-9)
    # the orientation fit absorbs the noise's mean turn, a fraction of a degree over 30 cameras
    assert 1.8 < res.rotation_rmse_deg <= 2.0 + 1e-9
    se3 = ate(stamps, est_T, stamps, gt_T, sim3=False)
    assert se3.rmse_m > 0.1  # without scale the half-size estimate cannot fit


def test_ate_skips_lost_poses_and_unmatched_stamps() -> None:
    gt_p, est_p, rmse = _hand_case()
    stamps = np.arange(6) * 100 * MS
    est_T = np.concatenate([_poses(est_p), np.full((1, 4, 4), np.nan), _poses(est_p[:1])])
    est_stamps = np.r_[stamps, 50 * MS, 10_000 * MS]  # a lost pose, and one far from any gt
    res = ate(est_stamps, est_T, stamps, _poses(gt_p))
    assert res.n_matched == 6
    assert res.rmse_m == pytest.approx(rmse, abs=1e-12)
    assert res.est_index.tolist() == [0, 1, 2, 3, 4, 5]


def test_ate_too_few_matches_names_the_problem() -> None:
    with pytest.raises(DataError, match=r"only 0 of 3 .* within 0.1 s"):
        ate(np.array([0, 1, 2]) * 10**9, _poses(np.zeros((3, 3))),
            np.array([10, 11, 12]) * 10**9, _poses(np.zeros((3, 3))))


def _smooth_gt(n: int) -> np.ndarray:
    k = np.arange(n)[:, None]
    return _poses(np.hstack([0.01 * k, 0.02 * np.sin(0.1 * k), 0.005 * k]),
                  np.hstack([0.02 * k, 0.01 * k, np.zeros((n, 1))]))


def test_rpe_of_one_displaced_frame_matches_hand_computation() -> None:
    n, k = 20, 7
    gt_T = _smooth_gt(n)
    stamps = np.arange(n) * 33 * MS
    # The estimate lives in another world frame (RPE needs no alignment); frame k is off by d in
    # its own camera frame, and one pose later is rotated by 1.5 degrees about its own axis.
    G = _rigid((0.3, -0.2, 0.5), (2.0, 1.0, -1.0))
    est_T = np.einsum("ij,njk->nik", G, gt_T)
    d = np.array([0.006, -0.008, 0.0])  # |d| = 1 cm
    est_T[k] = est_T[k] @ _rigid((0.0, 0.0, 0.0), tuple(d))
    est_T[k + 5] = est_T[k + 5] @ _rigid((0.0, 0.0, np.radians(1.5)), (0.0, 0.0, 0.0))
    res = rpe(stamps + 2 * MS, est_T, stamps, gt_T)
    assert res.n_pairs == n - 1 and res.delta == 1
    expected_t = np.zeros(n - 1)
    expected_t[[k - 1, k]] = 0.01  # the pairs into and out of frame k
    assert np.allclose(res.trans_errors_m[:k + 3], expected_t[:k + 3], atol=1e-12)
    expected_r = np.zeros(n - 1)
    expected_r[[k + 4, k + 5]] = 1.5
    assert np.allclose(res.rot_errors_deg, expected_r, atol=1e-6)
    assert res.rot_rmse_deg == pytest.approx(np.sqrt(2 * 1.5 ** 2 / (n - 1)), abs=1e-6)
    assert res.stamps_ns[0] == 2 * MS
    assert res.to_dict()["n_pairs"] == n - 1


def test_rpe_skips_lost_poses_applies_scale_and_delta() -> None:
    n = 12
    gt_T = _smooth_gt(n)
    stamps = np.arange(n) * 33 * MS
    est_T = gt_T.copy()
    est_T[:, :3, 3] *= 0.5  # a monocular estimate at half scale
    est_T[4] = np.nan  # lost
    res = rpe(stamps, est_T, stamps, gt_T, scale=2.0)
    assert res.n_pairs == n - 2  # 11 matched poses
    assert res.trans_rmse_m == pytest.approx(0.0, abs=1e-12)
    assert rpe(stamps, est_T, stamps, gt_T).trans_rmse_m > 1e-3  # without the scale
    res2 = rpe(stamps, est_T, stamps, gt_T, delta=3, scale=2.0)
    assert res2.n_pairs == n - 1 - 3 and res2.delta == 3


def test_rpe_needs_two_matched_poses() -> None:
    with pytest.raises(DataError, match=r"RPE: 1 of 1 .* need more than delta = 1"):
        rpe(np.array([0]), _poses(np.zeros((1, 3))), np.array([0]), _poses(np.zeros((1, 3))))
    with pytest.raises(ValueError, match="delta"):
        rpe(np.array([0, 1]), _poses(np.zeros((2, 3))), np.array([0, 1]), _poses(np.zeros((2, 3))), delta=0)


def test_path_length() -> None:
    assert path_length_m(_poses(np.array([[0, 0, 0], [3, 4, 0], [3, 4, 1]], float))) == pytest.approx(6.0)
    assert path_length_m(_poses(np.zeros((1, 3)))) == 0.0


def test_trajectory_and_error_plots_draw_the_data() -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from memgs_ros.evaluation.plots import plot_ate_errors, plot_trajectory_top

    gt_p, est_p, _ = _hand_case()
    fig = Figure()
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(1, 2)
    plot_trajectory_top(ax1, est_p, gt_p, plane="xz", keyframe_xyz=est_p[:2])
    lines = {ln.get_label(): ln for ln in ax1.get_lines()}
    assert set(lines) == {"ground truth", "estimate", "start", "keyframes"}
    assert np.allclose(lines["estimate"].get_ydata(), est_p[:, 2])
    assert np.allclose(lines["ground truth"].get_xdata(), gt_p[:, 0])
    plot_ate_errors(ax2, np.arange(6) * 0.1, np.array([0.03, 0.03, 0.04, 0.04, 0.05, 0.05]))
    assert any("RMSE 4.08 cm" in ln.get_label() for ln in ax2.get_lines())
    fig.canvas.draw()
    with pytest.raises(ValueError, match="plane"):
        plot_trajectory_top(ax1, est_p, plane="xw")


def test_rotation_error_is_aligned_by_the_orientations_on_a_rotation_only_trajectory() -> None:
    """A camera that mostly turns in place (fr1/rpy-like): its positions do not determine the world
    rotation, so the rotation error is read after the rotation fitted to the orientations. Exact
    orientations in a rotated world read 0; a 1-degree random turn of each camera reads ~1 degree."""
    rng = np.random.default_rng(7)
    n = 60
    gt_p = rng.normal(size=(n, 3)) * 0.002  # 2 mm of travel
    rv = rng.normal(size=(n, 3)) * 0.4
    gt_T = _poses(gt_p, rv)
    stamps = np.arange(n) * 33 * MS
    G = _rigid((0.3, -0.5, 0.5), (2.0, 0.0, -1.0))
    est_T = np.einsum("ij,njk->nik", G, gt_T)
    est_T[:, :3, 3] += rng.normal(size=(n, 3)) * 0.001  # 1 mm of position noise
    res = ate(stamps, est_T, stamps, gt_T)
    assert res.rotation_rmse_deg == pytest.approx(0.0, abs=1e-6)
    assert np.allclose(align_rotations(est_T[:, :3, :3], gt_T[:, :3, :3]), G[:3, :3].T, atol=1e-9)
    # the position fit alone leaves the world rotation undetermined: read through it, tens of degrees
    R_pos = res.alignment.R @ est_T[:, :3, :3]
    cos = (np.trace(np.swapaxes(gt_T[:, :3, :3], 1, 2) @ R_pos, axis1=1, axis2=2) - 1) / 2
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).mean() > 5.0
    # a rotation offset on the world side is what the alignment removes; per-camera noise stays
    tilt = Rotation.from_rotvec(rng.normal(size=(n, 3)) * np.radians(1.0)).as_matrix()
    est_T[:, :3, :3] = est_T[:, :3, :3] @ tilt
    noisy = ate(stamps, est_T, stamps, gt_T)
    expected = np.degrees(np.linalg.norm(Rotation.from_matrix(tilt).as_rotvec(), axis=1))
    assert noisy.rotation_rmse_deg == pytest.approx(float(np.sqrt(np.mean(expected ** 2))), rel=0.1)
