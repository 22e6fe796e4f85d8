"""Which way the colour camera's rows are read, checked on the frames themselves.

The configured ``rolling_shutter_readout_s`` says how long a rolling shutter takes from the first
row to the last, and that it reads them top to bottom. Some inputs read them bottom to top: a
sensor mounted upside down whose driver rotates the image, or a recording played backward
(``memgs run --repeat``: every other pass of a long flight). The correction set for the camera
then doubles the skew instead of removing it: fr1/rpy played forward and back five times, tracker
only, gave 6.6 cm ATE and 54 keyframes, against 1.3 cm and 35 with each pass's direction set by hand.

So on frames turning fast enough for the skew to show, the tracker also optimises the pose with the
keypoints corrected the other way and weighs the two reprojection errors
(:meth:`ReadoutDirection.vote`); when the evidence for the other way adds up, the direction flips.
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from memgs_ros.core.tracking.features.features import FrameFeatures, unroll_rolling_shutter

__all__ = ["ReadoutDirection", "check_other_direction", "median_reprojection_px", "refine_with_readout"]

logger = logging.getLogger(__name__)


@dataclass
class ReadoutDirection:
    """The readout in use (``readout_now_s``) and the evidence for flipping it; owned by one tracker.

    The evidence is a CUSUM of log(error now / error the other way) over the checked frames: a frame
    read the way in use adds a clearly negative term and the sum stays at 0; after a turn of the
    input's direction each frame adds a little (near the turn the camera is slow and the two errors
    differ by 5-20 %), and the sum crosses ``flip_evidence`` within about ten frames.
    """

    readout_s: float  # configured: > 0 top to bottom, < 0 bottom to top, 0 global shutter
    auto: bool = True  # check the direction on the frames (False: always the configured one)
    flip_evidence: float = 0.5  # the CUSUM that flips the direction
    drift: float = 0.02  # taken off every term: equal errors (slow frames) add nothing up
    min_skew_px: float = 1.5  # check only frames whose skew at the image's top and bottom rows reaches this
    idle_stride: int = 2  # while there is no evidence, check every this many turning frames (each check
    # costs a pose optimisation); once there is, every one
    sign: int = 1
    flips: int = 0
    checks: int = 0
    evidence: float = 0.0
    held_other: int = 0  # frames posed the other way before a flip, after the first (check_other_direction)
    _turning: int = 0  # turning frames seen

    @property
    def readout_now_s(self) -> float:
        return self.sign * self.readout_s

    def worth_checking(self, omega_c: np.ndarray, fx: float) -> bool:
        """Whether to check this frame: it turns at ``omega_c`` [3] rad/s fast enough for the skew to
        tell the directions apart (a rotation moves the first and last rows by about
        |omega| * fx * readout / 2 pixels), and it is its turn (``idle_stride``)."""
        if not (self.auto and self.readout_s != 0.0
                and float(np.linalg.norm(omega_c)) * fx * abs(self.readout_s) * 0.5 >= self.min_skew_px):
            return False
        self._turning += 1
        return self.evidence > 0.0 or self._turning % self.idle_stride == 0

    def vote(self, err_now: float, err_other: float) -> bool:
        """One frame's check: the reprojection error (median, pixels at level 0) with the direction in
        use and with the other one. True when this frame's evidence flipped the direction."""
        if not (np.isfinite(err_now) and np.isfinite(err_other) and err_now > 0 and err_other > 0):
            return False
        self.checks += 1
        self.evidence = max(0.0, self.evidence + float(np.log(err_now / err_other)) - self.drift)
        if self.evidence < self.flip_evidence:
            return False
        self.sign = -self.sign
        self.flips += 1
        self.evidence = 0.0
        return True


def median_reprojection_px(K: np.ndarray, T_cw: np.ndarray, p_w: np.ndarray, uv: np.ndarray,
                           inv_sigma: np.ndarray) -> float:
    """Median reprojection error of points p_w [K, 3] observed at uv [K, 2] (weights inv_sigma [K]),
    in level-0 pixels; NaN without points. Lean: it runs twice on every checked frame."""
    if len(uv) == 0:
        return float("nan")
    p_c = p_w @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = np.maximum(p_c[:, 2], 1e-6)
    du = K[0, 0] * p_c[:, 0] / z + K[0, 2] - uv[:, 0]
    dv = K[1, 1] * p_c[:, 1] / z + K[1, 2] - uv[:, 1]
    return float(np.median(np.sqrt(du * du + dv * dv) * inv_sigma))


Fit = tuple[FrameFeatures, np.ndarray, np.ndarray]  # (corrected features, T_cw [4, 4], inlier mask [K])


def check_other_direction(readout: ReadoutDirection, raw: FrameFeatures, in_use: Fit,
                          p_w: np.ndarray, kp_idx: np.ndarray, omega_c: np.ndarray, K: np.ndarray, height: int,
                          optimise: Callable[[FrameFeatures], tuple[np.ndarray, np.ndarray]],
                          inv_sigma: np.ndarray) -> Fit:
    """One frame's check: ``raw``'s keypoints corrected the other way, the pose re-optimised on the
    same matches (points p_w [K, 3] at keypoints kp_idx [K], by ``optimise``), and the
    two fits' median errors over the points either kept weighed by ``readout.vote``. Returns the fit
    of the direction in use afterwards (``in_use``, or the other one when this vote flipped it), or,
    once the direction has flipped before and while the evidence for flipping again builds, the other
    fit of a frame it suits better."""
    feats, T, inl = in_use
    other = unroll_rolling_shutter(raw, K, omega_c, -readout.readout_now_s, height)
    T_o, inl_o = optimise(other)
    both = inl | inl_o
    kp, w = kp_idx[both], inv_sigma[both]
    err_now = median_reprojection_px(K, T, p_w[both], feats.uv[kp], w)
    err_other = median_reprojection_px(K, T_o, p_w[both], other.uv[kp], w)
    if not readout.vote(err_now, err_other):
        # An input that has turned once is a replay with turns: while the evidence builds again, a frame
        # that fits the other way better keeps that fit, so the frames between its next turn and the
        # flip (6-10 on fr1/rpy) are posed as after it. Before any flip (every camera, one pass of a
        # recording) a frame keeps the direction in use: there, a frame favouring the other way is noise.
        if readout.flips and readout.evidence > 0.0 and err_other < err_now:
            readout.held_other += 1
            return other, T_o, inl_o
        return in_use
    logger.info("rolling shutter: the frames read their rows %s; correcting that way from now on",
                "top to bottom" if readout.readout_now_s > 0 else "bottom to top")
    return other, T_o, inl_o


def refine_with_readout(readout: ReadoutDirection, raw: FrameFeatures, p_w: np.ndarray, outcome: Any,
                        matcher: Any, omega_c: np.ndarray) -> Fit:
    """``raw``'s keypoints corrected with the frame's own angular velocity ``omega_c`` [3] (the first
    correction used the previous frame's; on fr1/rpy it changes by up to 50 % a frame) and the pose
    re-optimised by ``matcher`` (a LocalMapMatcher) on the outcome's matches (points p_w [K, 3]); on
    a frame worth it, the other direction checked too (``check_other_direction``). Returns the fit
    of the direction in use."""
    K, height, kp_idx = matcher.K, matcher.camera.height, outcome.kp_idx

    def optimise(f: FrameFeatures) -> tuple[np.ndarray, np.ndarray]:
        return matcher.optimise(outcome.T_cw, p_w, f, kp_idx, rounds=2)

    inv_sigma = matcher.inv_sigma(raw.octave[kp_idx])
    feats = unroll_rolling_shutter(raw, K, omega_c, readout.readout_now_s, height)
    T, inl = optimise(feats)
    if not readout.worth_checking(omega_c, K[0, 0]):
        return feats, T, inl
    return check_other_direction(readout, raw, (feats, T, inl), p_w, kp_idx, omega_c, K, height, optimise, inv_sigma)
