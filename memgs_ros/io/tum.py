"""TUM RGB-D folders: rgb.txt / depth.txt / groundtruth.txt plus PNG images.

Layout (reference section 6): ``rgb.txt`` and ``depth.txt`` list ``timestamp path`` lines,
``groundtruth.txt`` lists ``timestamp tx ty tz qx qy qz qw`` (camera-to-world of the RGB
optical frame), '#' starts a comment. Depth PNGs are uint16, value / depth_factor = metres,
0 = no measurement (kept as 0, which ``Frame`` treats as invalid).

The camera comes from, in order: the ``camera`` argument, a ``camera.json`` beside the lists
(written by ``memgs_ros.io.synthetic.write_tum_folder``; format in ``write_camera_json``), the
folder name (``freiburg1/2/3`` -> ``TUM_CAMERAS``), the ``default_camera`` argument (a
configured calibration). A camera of another resolution than the images is rescaled to them
(same aspect ratio). The depth factor: argument, camera.json, folder name, 5000.
"""
from __future__ import annotations

import json
import logging
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from memgs_ros.core.geometry.camera import TUM_CAMERAS, TUM_DEPTH_FACTORS, PinholeCamera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.geometry.poses import interpolate_poses, pose_to_tq, quat_xyzw_to_rotmat
from memgs_ros.core.geometry.view import DepthUnits
from memgs_ros.core.metrics.trajectory import associate as associate_stamps
from memgs_ros.errors import DataError
from memgs_ros.io.skips import SkipLog

logger = logging.getLogger(__name__)

CAMERA_JSON = "camera.json"
DEFAULT_DEPTH_FACTOR = 5000.0
_NS = 1_000_000_000


def parse_stamp_ns(text: str) -> int:
    """Decimal seconds ('1305031229.528748') -> integer ns, exactly (no float rounding)."""
    s = text.strip()
    m = re.fullmatch(r"(\d+)(?:\.(\d*))?", s)
    if m is None:
        # rare forms (exponent, sign): go through float, accepting sub-microsecond rounding
        return round(float(s) * 1e9)
    frac = (m.group(2) or "")[:9].ljust(9, "0")
    return int(m.group(1)) * _NS + int(frac)


def format_stamp(stamp_ns: int) -> str:
    """Integer ns -> TUM's 'seconds.microseconds' text."""
    sec, nsec = divmod(int(stamp_ns), _NS)
    return f"{sec}.{nsec // 1000:06d}"


def format_pose_line(stamp: str, T_wc: np.ndarray) -> str:
    """One trajectory line 'stamp tx ty tz qx qy qz qw' (camera-to-world, 9 decimals): the one
    TUM pose format (groundtruth.txt, estimated trajectories); ``stamp`` as the caller writes it."""
    t, q = pose_to_tq(T_wc)
    return f"{stamp} " + " ".join(f"{x:.9f}" for x in (*t, *q))


def _data_lines(path: Path) -> Iterator[tuple[int, list[str]]]:
    """(line number, whitespace-split fields) of every non-comment, non-blank line."""
    try:
        text = path.read_text()
    except FileNotFoundError as err:
        raise DataError(f"{path}: file not found") from err
    except (OSError, UnicodeDecodeError) as err:
        raise DataError(f"{path}: cannot read ({err})") from err
    for i, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        yield i, line.split()


def read_file_list(path: str | Path) -> tuple[np.ndarray, list[str]]:
    """rgb.txt / depth.txt -> (stamps_ns [N] int64 increasing, relative paths [N])."""
    path = Path(path)
    stamps: list[int] = []
    names: list[str] = []
    for lineno, parts in _data_lines(path):
        if len(parts) < 2:
            raise DataError(f"{path}:{lineno}: expected 'timestamp filename', got {' '.join(parts)!r}")
        try:
            stamps.append(parse_stamp_ns(parts[0]))
        except ValueError as err:
            raise DataError(f"{path}:{lineno}: bad timestamp {parts[0]!r}") from err
        names.append(parts[1])
    order = np.argsort(np.asarray(stamps, dtype=np.int64), kind="stable")
    return np.asarray(stamps, dtype=np.int64)[order], [names[i] for i in order]


def read_trajectory(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """groundtruth.txt (or any TUM trajectory) -> (stamps_ns [M] int64 increasing, T_wc [M, 4, 4])."""
    path = Path(path)
    stamps: list[int] = []
    rows: list[list[float]] = []
    for lineno, parts in _data_lines(path):
        if len(parts) != 8:
            raise DataError(f"{path}:{lineno}: expected 'timestamp tx ty tz qx qy qz qw' (8 fields), got {len(parts)}")
        try:
            stamp = parse_stamp_ns(parts[0])
            vals = [float(x) for x in parts[1:]]
        except ValueError as err:
            raise DataError(f"{path}:{lineno}: unparsable number in {' '.join(parts)!r}") from err
        q = np.asarray(vals[3:])
        if not np.all(np.isfinite(vals)) or not 0.5 < np.linalg.norm(q) < 1.5:
            raise DataError(f"{path}:{lineno}: non-finite value or non-unit quaternion in {' '.join(parts)!r}")
        stamps.append(stamp)
        rows.append(vals)
    st = np.asarray(stamps, dtype=np.int64)
    order = np.argsort(st, kind="stable")
    st = st[order]
    if len(st) > 1 and np.any(np.diff(st) == 0):
        # duplicated stamps would make interpolation ambiguous: keep the first of each
        keep = np.concatenate([[True], np.diff(st) > 0])
        order, st = order[keep], st[keep]
    v = np.asarray(rows, dtype=np.float64).reshape(-1, 7)[order]
    T = np.tile(np.eye(4), (len(v), 1, 1))
    if len(v):
        T[:, :3, :3] = quat_xyzw_to_rotmat(v[:, 3:7])
        T[:, :3, 3] = v[:, :3]
    return st, T


def associate(stamps_a: np.ndarray, stamps_b: np.ndarray, max_dt_ns: int) -> list[tuple[int, int]]:
    """One-to-one nearest-stamp matching: pairs (i, j) with |a_i - b_j| <= max_dt_ns, in
    increasing order of i (greedy by smallest difference; see ``core.trajectory.associate``)."""
    ia, ib = associate_stamps(stamps_a, stamps_b, max_dt_ns)
    return sorted(zip(ia.tolist(), ib.tolist()))


def camera_from_name(name: str) -> tuple[PinholeCamera, float] | None:
    """'rgbd_dataset_freiburg1_rpy' -> (TUM_FR1, 5000.0); None when the name says nothing."""
    m = re.search(r"freiburg([123])", name)
    if m is None:
        return None
    key = f"fr{m.group(1)}"
    return TUM_CAMERAS[key], TUM_DEPTH_FACTORS[key]


def folder_guess(path: Path) -> tuple[PinholeCamera, float] | None:
    """A TUM folder's camera and depth PNG units a metre from its camera.json, else its name."""
    cam_file = path / CAMERA_JSON
    return (read_camera_json(cam_file) if cam_file.is_file() else None) or camera_from_name(path.resolve().name)


def folder_depth_factor(path: Path) -> float:
    """The depth PNG units a metre of the TUM folder ``path``: camera.json, folder name, else 5000."""
    guess = folder_guess(path)
    return guess[1] if guess else DEFAULT_DEPTH_FACTOR


def write_camera_json(path: Path, camera: PinholeCamera, depth_factor: float) -> None:
    """``camera.json``: one JSON object with ``width``, ``height`` (px), ``fx``, ``fy``, ``cx``,
    ``cy`` (px), ``dist`` (5 plumb_bob or 8 rational_polynomial coefficients, OpenCV order
    k1 k2 p1 p2 k3 [k4 k5 k6]) and ``depth_factor`` (depth PNG units per metre; optional when
    read, default 5000)."""
    data = {"width": camera.width, "height": camera.height, "fx": camera.fx, "fy": camera.fy,
            "cx": camera.cx, "cy": camera.cy, "dist": list(camera.dist), "depth_factor": depth_factor}
    path.write_text(json.dumps(data, indent=1) + "\n")


def read_camera_json(path: Path) -> tuple[PinholeCamera, float]:
    try:
        data = json.loads(path.read_text())
        cam = PinholeCamera(int(data["width"]), int(data["height"]), float(data["fx"]), float(data["fy"]),
                            float(data["cx"]), float(data["cy"]), tuple(float(x) for x in data["dist"]))  # type: ignore[arg-type]
        return cam, float(data.get("depth_factor", DEFAULT_DEPTH_FACTOR))
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise DataError(f"{path}: bad camera file ({err})") from err


def load_rgb(path: Path) -> np.ndarray:
    """Colour PNG/JPEG -> [H, W, 3] uint8 RGB."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise DataError(f"{path}: missing or unreadable image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def load_depth(path: Path, depth_factor: float) -> np.ndarray:
    """16-bit depth PNG -> [H, W] float32 metres, 0 where there is no measurement."""
    return (load_depth_units(path).astype(np.float32) / np.float32(depth_factor)).astype(np.float32)


def load_depth_units(path: Path) -> np.ndarray:
    """16-bit depth PNG -> [H, W] uint16 as stored (the folder's depth factor per metre, 0 = none)."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DataError(f"{path}: missing or unreadable depth image")
    if img.ndim != 2 or img.dtype != np.uint16:
        raise DataError(f"{path}: depth must be a single-channel 16-bit PNG, got {img.dtype} {img.shape}")
    return img


@dataclass(frozen=True)
class TumEntry:
    """One associated frame: stamps in ns, paths relative to the folder (depth None in RGB-only mode)."""

    stamp_ns: int
    rgb_path: str
    depth_stamp_ns: int | None
    depth_path: str | None


class TumFolder:
    """A TUM RGB-D folder as a lazy frame source (images load while iterating).

    Frames are the RGB images associated one-to-one with a depth image within ``max_dt_s``
    (``with_depth=False``: every RGB image, depth None), stamped with the RGB time, with
    ground truth interpolated at that time (None outside the ground-truth range or across
    a gap longer than ``gt_max_gap_s``). A frame whose image is missing, unreadable or of another
    size is skipped and counted in ``skipped`` by kind (``strict``: DataError instead).
    ``raw_depth``: frames carry the depth PNG as stored (:class:`DepthUnits`, the folder's depth
    factor per metre) instead of float metres, for a player that publishes it as 16UC1 unchanged.
    """

    def __init__(self, path: str | os.PathLike[str], camera: PinholeCamera | None = None,
                 depth_factor: float | None = None,
                 max_dt_s: float = 0.02, with_depth: bool = True, gt_max_gap_s: float = 0.1,
                 max_frames: int | None = None, default_camera: PinholeCamera | None = None,
                 strict: bool = False, raw_depth: bool = False) -> None:
        self.path = Path(path)
        self.raw_depth = raw_depth
        self.strict = strict
        self._skips = SkipLog(str(self.path), strict)
        self.skipped = self._skips.counts  # frames skipped while iterating, by kind
        if not self.path.is_dir():
            raise DataError(f"{self.path}: not a directory (expected a TUM RGB-D folder)")
        self.name = self.path.name
        from_file = (self.path / CAMERA_JSON).is_file()
        from_name = camera_from_name(self.path.resolve().name)
        guess = folder_guess(self.path)
        self.depth_factor = float(depth_factor if depth_factor is not None
                                  else guess[1] if guess else DEFAULT_DEPTH_FACTOR)
        if not self.depth_factor > 0:
            raise DataError(f"{self.path}: depth factor must be positive, got {self.depth_factor}")
        # Where the camera comes from ("" = nowhere: iterating raises DataError).
        self.camera_origin = ("argument" if camera is not None else CAMERA_JSON if from_file
                              else "folder name" if from_name else "default" if default_camera is not None else "")
        self._camera = camera if camera is not None else guess[0] if guess else default_camera
        self._camera_checked = camera is not None

        rgb_stamps, rgb_names = read_file_list(self.path / "rgb.txt")
        entries: list[TumEntry] = []
        if with_depth:
            depth_stamps, depth_names = read_file_list(self.path / "depth.txt")
            for i, j in associate(rgb_stamps, depth_stamps, round(max_dt_s * 1e9)):
                entries.append(TumEntry(int(rgb_stamps[i]), rgb_names[i], int(depth_stamps[j]), depth_names[j]))
        else:
            entries = [TumEntry(int(s), n, None, None) for s, n in zip(rgb_stamps, rgb_names)]
        if max_frames is not None:
            entries = entries[:max_frames]
        if not entries:
            raise DataError(f"{self.path}: no frames (no RGB images{' associated with depth' if with_depth else ''})")
        self.entries: tuple[TumEntry, ...] = tuple(entries)

        gt_file = self.path / "groundtruth.txt"
        if gt_file.is_file():
            self._gt_stamps, self._gt_poses = read_trajectory(gt_file)
        else:
            logger.info("%s: no groundtruth.txt; frames carry no ground truth", self.path)
            self._gt_stamps, self._gt_poses = np.zeros(0, np.int64), np.zeros((0, 4, 4))
        q = np.array([e.stamp_ns for e in self.entries], dtype=np.int64)
        self._frame_gt, self._frame_gt_valid = interpolate_poses(
            self._gt_stamps, self._gt_poses, q, round(gt_max_gap_s * 1e9))

    @property
    def camera(self) -> PinholeCamera:
        """The colour camera; a preset is rescaled when the images are not its size."""
        if not self._camera_checked:
            img = load_rgb(self.path / self.entries[0].rgb_path)
            h, w = img.shape[:2]
            if self._camera is None:
                raise DataError(f"{self.path}: cannot tell the camera: no {CAMERA_JSON}, folder name has no "
                                "freiburg1/2/3 and no camera was given")
            try:
                self._camera = self._camera.fitted(w, h)
            except DataError as err:
                raise DataError(f"{self.path}: {err} ({self.camera_origin})") from err
            self._camera_checked = True
        assert self._camera is not None
        return self._camera

    def __len__(self) -> int:
        return len(self.entries)

    def __iter__(self) -> Iterator[Frame]:
        _ = self.camera  # an unknown camera fails the whole folder, not each frame
        for k in range(len(self.entries)):
            try:
                frame = self.load(k)
            except DataError:
                if self.strict:
                    raise
                continue  # counted in ``skipped``
            yield frame

    def frame_stamps(self) -> np.ndarray:
        """[N] int64 the stamps of the frames, in order (unreadable ones included)."""
        return np.array([e.stamp_ns for e in self.entries], dtype=np.int64)

    def load(self, k: int) -> Frame:
        """Frame ``k`` of ``entries`` alone. An unreadable or mis-sized one is counted in
        ``skipped`` and raises DataError (with ``strict``: the skip's own DataError)."""
        camera = self.camera
        e = self.entries[k]
        try:
            rgb = load_rgb(self.path / e.rgb_path)
            depth: np.ndarray | DepthUnits | None = None
            if e.depth_path is not None:
                depth = (DepthUnits(load_depth_units(self.path / e.depth_path), self.depth_factor) if self.raw_depth
                         else load_depth(self.path / e.depth_path, self.depth_factor))
        except DataError as err:
            self._skips.skip("unreadable_image", str(err))
            raise
        gt = self._frame_gt[k].copy() if self._frame_gt_valid[k] else None
        try:
            return Frame(e.stamp_ns, rgb, depth, camera, gt)
        except DataError as err:
            self._skips.skip("size_mismatch", f"{self.path / e.rgb_path}: {err}")
            raise

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray]:
        """The whole ground-truth trajectory: (stamps_ns [M], T_wc [M, 4, 4]); empty when absent."""
        return self._gt_stamps.copy(), self._gt_poses.copy()

    @property
    def gt_coverage(self) -> float:
        """Fraction of frames that carry ground truth."""
        return float(np.mean(self._frame_gt_valid)) if len(self._frame_gt_valid) else 0.0


__all__ = [
    "TumEntry",
    "TumFolder",
    "associate",
    "camera_from_name",
    "folder_depth_factor",
    "format_pose_line",
    "format_stamp",
    "load_depth",
    "load_depth_units",
    "load_rgb",
    "parse_stamp_ns",
    "read_camera_json",
    "read_file_list",
    "read_trajectory",
    "write_camera_json",
]
