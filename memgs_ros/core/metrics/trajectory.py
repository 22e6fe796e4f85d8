"""Trajectory evaluation: timestamp association, Umeyama alignment, ATE, RPE (reference sec. 7).

All poses are ``T_wc`` (camera-to-world) 4x4 float64; stamps are integer nanoseconds.
The ATE is the RMSE of camera positions after aligning the estimate to the ground truth with
the least-squares rigid (SE(3)) or similarity (Sim(3), monocular) transform of Umeyama (1991),
over pairs associated one-to-one within ``max_dt_s`` (0.1 s as in the TUM tools).
The RPE compares the relative motion between matched frames ``delta`` apart with the ground
truth's (Sturm et al. 2012); it needs no alignment and shows frame-to-frame jitter that the
ATE averages away.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from memgs_ros.errors import DataError

__all__ = ["AteResult", "RpeResult", "Sim3Alignment", "align_rotations", "align_umeyama", "associate", "ate",
           "path_length_m", "rpe"]

_MIN_ALIGN_POINTS = 3  # a rotation is not determined by fewer non-collinear points


@dataclass(frozen=True, eq=False)
class Sim3Alignment:
    """``p_ref = s * R @ p_est + t``. R: [3, 3] rotation, t: [3], s: scale (1.0 for SE(3))."""

    R: np.ndarray
    t: np.ndarray
    s: float = 1.0

    def as_matrix(self) -> np.ndarray:
        """The 4x4 similarity [[s R, t], [0, 1]]."""
        T = np.eye(4)
        T[:3, :3] = self.s * self.R
        T[:3, 3] = self.t
        return T

    def apply(self, points: np.ndarray) -> np.ndarray:
        """points: [M, 3] -> [M, 3] in the reference frame."""
        return self.s * np.asarray(points, dtype=np.float64) @ self.R.T + self.t


@dataclass(frozen=True, eq=False)
class AteResult:
    """Absolute trajectory error of matched pairs after alignment. Lengths in metres.

    errors_m: [n] position error per matched pair; stamps_ns: [n] the estimate's stamps;
    est_index / gt_index: [n] indices of the pairs into the inputs.
    """

    rmse_m: float
    mean_m: float
    median_m: float
    max_m: float
    n_matched: int
    alignment: Sim3Alignment
    errors_m: np.ndarray
    rotation_rmse_deg: float
    stamps_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    est_index: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    gt_index: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (scalars, alignment, per-pair errors)."""
        return {
            "rmse_m": self.rmse_m, "mean_m": self.mean_m, "median_m": self.median_m,
            "max_m": self.max_m, "n_matched": self.n_matched,
            "rotation_rmse_deg": self.rotation_rmse_deg,
            "alignment": {"R": self.alignment.R.tolist(), "t": self.alignment.t.tolist(),
                          "s": self.alignment.s},
            "stamps_ns": [int(s) for s in self.stamps_ns],
            "errors_m": [float(e) for e in self.errors_m],
        }


@dataclass(frozen=True, eq=False)
class RpeResult:
    """Relative pose error over ``delta`` matched frames.

    trans_errors_m: [n] translation error of each pair's relative motion; rot_errors_deg: [n]
    its rotation angle; stamps_ns: [n] the estimate's stamp at the start of each pair.
    """

    trans_rmse_m: float
    rot_rmse_deg: float
    trans_median_m: float
    n_pairs: int
    delta: int
    trans_errors_m: np.ndarray
    rot_errors_deg: np.ndarray
    stamps_ns: np.ndarray

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (scalars and per-pair errors)."""
        return {"trans_rmse_m": self.trans_rmse_m, "rot_rmse_deg": self.rot_rmse_deg,
                "trans_median_m": self.trans_median_m, "n_pairs": self.n_pairs, "delta": self.delta,
                "stamps_ns": [int(s) for s in self.stamps_ns],
                "trans_errors_m": [float(e) for e in self.trans_errors_m],
                "rot_errors_deg": [float(e) for e in self.rot_errors_deg]}


def associate(stamps_a_ns: np.ndarray, stamps_b_ns: np.ndarray,
              max_dt_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one association of two stamp lists by nearest time.

    stamps_a_ns: [A], stamps_b_ns: [B] integer ns (any order). Candidate pairs with
    |dt| <= max_dt_ns are taken greedily from the smallest |dt| (ties: lower index first),
    each stamp used at most once, as the TUM ``associate.py`` does.
    Returns (ia [n], ib [n]) int64 indices into the inputs, sorted by ia.
    """
    a = np.asarray(stamps_a_ns, dtype=np.int64).reshape(-1)
    b = np.asarray(stamps_b_ns, dtype=np.int64).reshape(-1)
    empty = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    if max_dt_ns < 0:
        raise ValueError(f"associate: max_dt_ns must be >= 0, got {max_dt_ns}")
    if a.size == 0 or b.size == 0:
        return empty
    order_b = np.argsort(b, kind="stable")
    b_sorted = b[order_b]
    lo = np.searchsorted(b_sorted, a - max_dt_ns, side="left")
    hi = np.searchsorted(b_sorted, a + max_dt_ns, side="right")
    counts = hi - lo
    if counts.sum() == 0:
        return empty
    # All candidate pairs (a index, position in sorted b), built without a Python loop.
    cand_a = np.repeat(np.arange(a.size), counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    cand_bs = np.repeat(lo, counts) + offsets
    cand_b = order_b[cand_bs]
    dt = np.abs(a[cand_a] - b[cand_b])
    order = np.lexsort((cand_b, cand_a, dt))  # by |dt|, then a, then b
    used_a = np.zeros(a.size, dtype=bool)
    used_b = np.zeros(b.size, dtype=bool)
    ia: list[int] = []
    ib: list[int] = []
    for k in order:
        i, j = int(cand_a[k]), int(cand_b[k])
        if used_a[i] or used_b[j]:
            continue
        used_a[i] = used_b[j] = True
        ia.append(i)
        ib.append(j)
    ia_arr = np.asarray(ia, dtype=np.int64)
    ib_arr = np.asarray(ib, dtype=np.int64)
    s = np.argsort(ia_arr, kind="stable")
    return ia_arr[s], ib_arr[s]


def align_umeyama(est: np.ndarray,  # [M, 3]
                  ref: np.ndarray,  # [M, 3]
                  with_scale: bool = False) -> Sim3Alignment:
    """Least-squares ``ref ~ s R est + t`` (Umeyama 1991), s = 1 unless ``with_scale``.

    est, ref: [M, 3] corresponding points, M >= 3 and not all collinear. A reflection in the
    SVD solution is corrected by flipping the sign of the smallest singular direction.
    """
    x = np.asarray(est, dtype=np.float64)
    y = np.asarray(ref, dtype=np.float64)
    assert x.shape == y.shape and x.ndim == 2 and x.shape[1] == 3, (
        f"align_umeyama expects two [M, 3] arrays, got {x.shape} and {y.shape}")
    m = x.shape[0]
    if m < _MIN_ALIGN_POINTS:
        raise DataError(f"Umeyama alignment needs at least {_MIN_ALIGN_POINTS} point pairs, got {m}")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise DataError("Umeyama alignment got non-finite positions")
    mu_x, mu_y = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mu_x, y - mu_y
    cov = yc.T @ xc / m  # [3, 3] cross-covariance Sigma_xy of the paper
    U, d, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = 1.0
    if with_scale:
        var_x = float((xc * xc).sum() / m)
        if var_x <= 0.0:
            raise DataError("Sim(3) alignment is undefined: all estimated positions coincide")
        s = float(np.trace(np.diag(d) @ S) / var_x)
    t = mu_y - s * R @ mu_x
    return Sim3Alignment(R=R, t=t, s=s)


def align_rotations(R_est: np.ndarray,  # [M, 3, 3]
                    R_ref: np.ndarray,  # [M, 3, 3]
                    ) -> np.ndarray:  # [3, 3]
    """The world rotation R that best maps estimated orientations onto the reference ones,
    ``argmin_R sum ||R_ref_i - R R_est_i||_F^2`` (chordal): the rotation nearest to
    ``sum R_ref_i R_est_i^T`` (SVD, reflection corrected). R_est, R_ref: [M, 3, 3], M >= 1."""
    M = np.einsum("nij,nkj->ik", np.asarray(R_ref, np.float64), np.asarray(R_est, np.float64))
    U, _, Vt = np.linalg.svd(M)
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ S @ Vt


def _trajectories(fn: str, est_stamps_ns: np.ndarray, est_T_wc: np.ndarray, gt_stamps_ns: np.ndarray,
                  gt_T_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(est stamps [M] int64, est poses [M, 4, 4], gt stamps [K], gt poses [K, 4, 4]) as float64 /
    int64 arrays; AssertionError (naming ``fn``) when the shapes do not match."""
    est_T = np.asarray(est_T_wc, dtype=np.float64)
    gt_T = np.asarray(gt_T_wc, dtype=np.float64)
    est_s = np.asarray(est_stamps_ns, dtype=np.int64)
    gt_s = np.asarray(gt_stamps_ns, dtype=np.int64)
    assert est_T.ndim == 3 and est_T.shape[1:] == (4, 4) and est_T.shape[0] == est_s.shape[0], (
        f"{fn}: est_T_wc {est_T.shape} must be [M, 4, 4] with M = len(est_stamps_ns) = {est_s.shape[0]}")
    assert gt_T.ndim == 3 and gt_T.shape[1:] == (4, 4) and gt_T.shape[0] == gt_s.shape[0], (
        f"{fn}: gt_T_wc {gt_T.shape} must be [K, 4, 4] with K = len(gt_stamps_ns) = {gt_s.shape[0]}")
    return est_s, est_T, gt_s, gt_T


def ate(est_stamps_ns: np.ndarray,  # [M]
        est_T_wc: np.ndarray,  # [M, 4, 4]
        gt_stamps_ns: np.ndarray,  # [K]
        gt_T_wc: np.ndarray,  # [K, 4, 4]
        max_dt_s: float = 0.1, sim3: bool = False) -> AteResult:
    """Absolute trajectory error (translation RMSE after SE(3) or Sim(3) Umeyama alignment).

    Estimated poses with non-finite entries (lost tracking) are left out before association.
    Pairs are associated one-to-one within ``max_dt_s``. Also reports the RMSE of the
    rotation angle between estimate and ground truth, in degrees, after the world rotation fitted
    to the orientations (``align_rotations``), not the one fitted to the positions.
    Raises DataError when fewer than 3 pairs match.
    """
    est_s, est_T, gt_s, gt_T = _trajectories("ate", est_stamps_ns, est_T_wc, gt_stamps_ns, gt_T_wc)
    finite = np.isfinite(est_T).all(axis=(1, 2))
    keep = np.flatnonzero(finite)
    ia, ib = associate(est_s[keep], gt_s, round(max_dt_s * 1e9))
    ia = keep[ia]
    n = int(ia.size)
    if n < _MIN_ALIGN_POINTS:
        raise DataError(
            f"ATE: only {n} of {est_s.size} estimated poses match ground truth within {max_dt_s} s "
            f"(need {_MIN_ALIGN_POINTS}); check that both use the same clock")
    p_est = est_T[ia, :3, 3]
    p_gt = gt_T[ib, :3, 3]
    align = align_umeyama(p_est, p_gt, with_scale=sim3)
    err = np.linalg.norm(align.apply(p_est) - p_gt, axis=1)
    # The rotation error gets its own alignment, fitted to the orientations: positions do not
    # determine the world rotation of a rotation-dominant trajectory (fr1/rpy: 24.8 deg read after
    # the position fit for a trajectory whose orientations agree to ~1 deg).
    R_est, R_gt = est_T[ia, :3, :3], gt_T[ib, :3, :3]
    R_rel = np.swapaxes(R_gt, 1, 2) @ align_rotations(R_est, R_gt) @ R_est
    cos = np.clip((np.trace(R_rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    ang_deg = np.degrees(np.arccos(cos))
    return AteResult(
        rmse_m=float(np.sqrt(np.mean(err ** 2))), mean_m=float(err.mean()),
        median_m=float(np.median(err)), max_m=float(err.max()), n_matched=n, alignment=align,
        errors_m=err, rotation_rmse_deg=float(np.sqrt(np.mean(ang_deg ** 2))),
        stamps_ns=est_s[ia], est_index=ia, gt_index=ib)


def rpe(est_stamps_ns: np.ndarray,  # [M]
        est_T_wc: np.ndarray,  # [M, 4, 4]
        gt_stamps_ns: np.ndarray,  # [K]
        gt_T_wc: np.ndarray,  # [K, 4, 4]
        delta: int = 1, max_dt_s: float = 0.1, scale: float = 1.0) -> RpeResult:
    """Relative pose error between matched frames ``delta`` apart (translation and rotation RMSE).

    Poses are associated with the ground truth as in ``ate`` (non-finite ones left out first) and
    ordered by the estimate's stamp; each pair (i, i + delta) of that matched list gives
    ``E = (G_i^-1 G_j)^-1 (P_i^-1 P_j)`` with P the estimate and G the ground truth, and the
    errors are ``|t(E)|`` and the angle of ``R(E)``. A pair spans a lost frame when one was left
    out. ``scale`` multiplies the estimate's translations (monocular: the Sim(3) scale of ``ate``).
    Raises DataError when no pair is left.
    """
    if delta < 1:
        raise ValueError(f"rpe: delta must be >= 1, got {delta}")
    est_s, est_T, gt_s, gt_T = _trajectories("rpe", est_stamps_ns, est_T_wc, gt_stamps_ns, gt_T_wc)
    keep = np.flatnonzero(np.isfinite(est_T).all(axis=(1, 2)))
    ia, ib = associate(est_s[keep], gt_s, round(max_dt_s * 1e9))
    ia = keep[ia]
    order = np.argsort(est_s[ia], kind="stable")
    ia, ib = ia[order], ib[order]
    n = int(ia.size) - delta
    if n < 1:
        raise DataError(
            f"RPE: {ia.size} of {est_s.size} estimated poses match ground truth within {max_dt_s} s; "
            f"need more than delta = {delta}")
    P = est_T[ia].copy()
    P[:, :3, 3] *= scale
    G = gt_T[ib]
    rel_est = np.linalg.inv(P[:-delta]) @ P[delta:]  # [n, 4, 4]
    rel_gt = np.linalg.inv(G[:-delta]) @ G[delta:]
    E = np.linalg.inv(rel_gt) @ rel_est
    t_err = np.linalg.norm(E[:, :3, 3], axis=1)
    R = E[:, :3, :3]
    # atan2 of (sin, cos) keeps small angles exact (arccos near 1 loses half the digits).
    sin = 0.5 * np.linalg.norm(np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0],
                                         R[:, 1, 0] - R[:, 0, 1]], axis=1), axis=1)
    r_err = np.degrees(np.arctan2(sin, (np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0))
    return RpeResult(trans_rmse_m=float(np.sqrt(np.mean(t_err ** 2))),
                     rot_rmse_deg=float(np.sqrt(np.mean(r_err ** 2))),
                     trans_median_m=float(np.median(t_err)), n_pairs=n, delta=delta,
                     trans_errors_m=t_err, rot_errors_deg=r_err, stamps_ns=est_s[ia[:-delta]])


def path_length_m(T_wc: np.ndarray) -> float:
    """Length of the camera path: sum of distances between consecutive positions. T_wc: [M, 4, 4]."""
    T = np.asarray(T_wc, dtype=np.float64)
    if T.shape[0] < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1).sum())
