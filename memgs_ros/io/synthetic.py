"""Synthetic RGB-D sequences with exact ground truth: a textured room rendered by ray casting.

The scene is an axis-aligned room (floor, four walls, ceiling) with a few boxes on the
floor, world frame z up (REP-103). Every surface carries a procedural texture baked once
per scene into a texture atlas in surface coordinates (metres on the surface, 5 mm
texels): floor tiles and a rug, painted walls with framed posters, a door and a window,
ceiling panels and lamps, striped/labelled boxes, all with smooth value-noise blotches
and a baked soft light falloff. Textures are piecewise smooth with crisp edges (corners
for ORB, learnable for a Gaussian-splatting mapper), never per-pixel noise.

Rendering is vectorised numpy: one ray per pixel (or ``supersample``^2 rays per pixel for
the colour image), nearest hit among the room's inner faces and the boxes' outer faces,
then one bilinear atlas lookup (``cv2.remap``). Depth is the exact z of the hit point in
the camera frame at pixel centres (pixel (row i, col j) is the ray through u=j, v=i).

Spec strings for the CLIs (``parse_spec``)::

    synthetic                       all defaults
    synthetic:w=160,h=120,n=60,seed=0,noise=0.01,holes=0.05

keys: w, h (image size, px), n (frames), fps, seed, noise (depth noise std, m),
holes (fraction of depth pixels zeroed in random blobs), path (wobble, loop or orbit), amp (path translation scale,
1 = about 1.9 m of travel), rot (path rotation scale, 1 = yaw +-35 deg, pitch +-8 deg,
roll +-8 deg), aa (colour supersampling factor; 0 = auto: 2 up to 320x240, else 1), laps (the n
frames flown this many times on one clock: ``n * laps`` frames, each lap's images rendered once).
Defaults: 640x480, 120 frames at 30 fps, seed 0, no noise, no holes, path=wobble, laps=1.

``path=loop`` is a loop-closure sequence: the camera goes once round the room (about 10 m,
looking out at the walls and furniture) and then retraces the first ``LOOP_OVERLAP`` of the
round, so the last frames revisit the start views (``loop_revisit_frames``). ``path=orbit`` is the
same round without the retrace, closed: its frame n would be its frame 0, so ``laps`` flies it round
and round without a jump (a long flight over one room: ``synthetic:w=320,h=240,path=orbit,n=450,laps=40``
is 10 minutes at 30 fps).

The room geometry (6 x 5 x 2.7 m, six boxes) is fixed; the seed changes the textures and
the phases of the camera path. The camera is TUM fr3-like without distortion, scaled to
the image size; stamps start at SYNTH_START_NS and are whole microseconds.
"""
from __future__ import annotations

import math
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, fields, replace
from pathlib import Path

import cv2
import numpy as np

from memgs_ros.core.geometry.camera import TUM_FR3, PinholeCamera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.errors import ConfigError, DataError
from memgs_ros.io.image_decoding import metres_to_depth_units
from memgs_ros.io.synthetic_scene import TEXEL_M, SyntheticScene, build_scene
from memgs_ros.io.tum import CAMERA_JSON, format_pose_line, format_stamp, write_camera_json

# Synthetic stamps start here (a plausible wall-clock epoch, like TUM's), in ns.
SYNTH_START_NS = 1_700_000_000 * 1_000_000_000
SPEC_KEYS = {
    "w": "width", "h": "height", "n": "n_frames", "fps": "fps", "seed": "seed",
    "noise": "depth_noise_std_m", "holes": "hole_fraction", "amp": "path_amp", "rot": "path_rot",
    "aa": "supersample", "path": "path", "laps": "laps",
}
PATH_KINDS = ("wobble", "loop", "orbit")
MAX_LAPS = 100_000


@dataclass(frozen=True)
class SyntheticSpec:
    """What to generate. The camera is TUM fr3-like (no distortion) scaled to width x height."""

    width: int = 640
    height: int = 480
    n_frames: int = 120
    fps: float = 30.0
    seed: int = 0
    depth_noise_std_m: float = 0.0  # Gaussian, added to valid depth
    hole_fraction: float = 0.0  # fraction of depth pixels set to 0 in blobs
    path_amp: float = 1.0  # translation scale of the camera path
    path_rot: float = 1.0  # rotation scale of the camera path
    supersample: int = 0  # colour rays per pixel per axis; 0 = auto
    path: str = "wobble"  # "wobble": small closed path near x = -1.3; "loop": round the room and back
    laps: int = 1  # the n_frames flown this many times (n_frames * laps frames on one clock)

    def __post_init__(self) -> None:
        if self.width < 8 or self.height < 8:
            raise ConfigError(f"synthetic image size must be at least 8x8, got {self.width}x{self.height}")
        if self.n_frames < 1:
            raise ConfigError(f"synthetic n_frames must be >= 1, got {self.n_frames}")
        if not self.fps > 0:
            raise ConfigError(f"synthetic fps must be positive, got {self.fps}")
        if self.depth_noise_std_m < 0:
            raise ConfigError(f"synthetic depth noise must be >= 0, got {self.depth_noise_std_m}")
        if not 0.0 <= self.hole_fraction < 1.0:
            raise ConfigError(f"synthetic hole fraction must be in [0, 1), got {self.hole_fraction}")
        if not (0.0 <= self.path_amp <= 1.5 and 0.0 <= self.path_rot <= 2.0):
            raise ConfigError("synthetic path scales amp in [0, 1.5], rot in [0, 2]; "
                              f"got {self.path_amp}, {self.path_rot}")
        if self.path not in PATH_KINDS:
            raise ConfigError(f"synthetic path must be one of {PATH_KINDS}, got {self.path!r}")
        if not 1 <= self.laps <= MAX_LAPS:
            raise ConfigError(f"synthetic laps must be in [1, {MAX_LAPS}], got {self.laps}")
        if not 0 <= self.supersample <= 4:
            raise ConfigError(f"synthetic supersample must be 0 (auto) .. 4, got {self.supersample}")

    @property
    def camera(self) -> PinholeCamera:
        sx, sy = self.width / TUM_FR3.width, self.height / TUM_FR3.height
        return PinholeCamera(self.width, self.height, TUM_FR3.fx * sx, TUM_FR3.fy * sy,
                             (TUM_FR3.cx + 0.5) * sx - 0.5, (TUM_FR3.cy + 0.5) * sy - 0.5)

    @property
    def total_frames(self) -> int:
        """Frames of the whole sequence: ``n_frames`` a lap, ``laps`` laps."""
        return self.n_frames * self.laps

    @property
    def aa(self) -> int:
        if self.supersample:
            return self.supersample
        return 2 if self.width * self.height <= 320 * 240 else 1

    def to_string(self) -> str:
        """The spec string that ``parse_spec`` turns back into this spec."""
        # path and laps only when not the default, so default specs keep their old names
        defaults = {"path": "wobble", "laps": 1}
        parts = [f"{k}={getattr(self, f)}" for k, f in SPEC_KEYS.items()
                 if k not in defaults or getattr(self, f) != defaults[k]]
        return "synthetic:" + ",".join(parts)


def is_spec_string(text: str | os.PathLike[str]) -> bool:
    return isinstance(text, str) and (text == "synthetic" or text.startswith("synthetic:"))


def parse_spec(text: str) -> SyntheticSpec:
    """``synthetic[:key=value,...]`` -> SyntheticSpec (keys in the module docstring)."""
    if not is_spec_string(text):
        raise ConfigError(f"synthetic spec must start with 'synthetic', got {text!r}")
    body = text[len("synthetic:"):] if ":" in text else ""
    kwargs: dict[str, object] = {}
    types = {f.name: f.type for f in fields(SyntheticSpec)}
    for item in filter(None, (p.strip() for p in body.split(","))):
        key, sep, value = item.partition("=")
        if not sep or key.strip() not in SPEC_KEYS:
            raise ConfigError(f"synthetic spec {text!r}: bad item {item!r}; keys are {', '.join(SPEC_KEYS)}")
        name = SPEC_KEYS[key.strip()]
        if types[name] in ("str", str):
            kwargs[name] = value.strip()
            continue
        try:
            kwargs[name] = int(value) if types[name] in ("int", int) else float(value)
        except ValueError as err:
            raise ConfigError(f"synthetic spec {text!r}: {key}={value!r} is not a number") from err
    return SyntheticSpec(**kwargs)  # type: ignore[arg-type]


def _ray_dirs(camera: PinholeCamera, aa: int) -> np.ndarray:
    """Camera-frame rays [H*aa, W*aa, 3] float32 with z = 1, through sub-pixel sample centres."""
    j = (np.arange(camera.width * aa, dtype=np.float32) + 0.5) / aa - 0.5
    i = (np.arange(camera.height * aa, dtype=np.float32) + 0.5) / aa - 0.5
    x = (j - camera.cx) / camera.fx
    y = (i - camera.cy) / camera.fy
    d = np.empty((len(i), len(j), 3), np.float32)
    d[..., 0] = x[None, :]
    d[..., 1] = y[:, None]
    d[..., 2] = 1.0
    return d


def _box_window(lo: np.ndarray, hi: np.ndarray, T_cw: np.ndarray, dirs_c: np.ndarray) -> tuple[slice, slice] | None:
    """Rows/cols of the ray grid [Hs, Ws, 3] whose rays can hit the box, or None if none can.

    Projects the 8 corners; when a corner is behind (or at) the camera the whole grid is kept.
    Rays with z = 1 map x/z, y/z linearly to grid columns/rows, so the corner hull bounds them.
    """
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    pc = corners @ T_cw[:3, :3].T + T_cw[:3, 3]
    hs, ws = dirs_c.shape[:2]
    if np.any(pc[:, 2] <= 1e-3):
        return slice(0, hs), slice(0, ws)
    x, y = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
    xs, ys = dirs_c[0, :, 0], dirs_c[:, 0, 1]  # increasing
    c0 = max(int(np.searchsorted(xs, x.min())) - 1, 0)
    c1 = min(int(np.searchsorted(xs, x.max())) + 1, ws)
    r0 = max(int(np.searchsorted(ys, y.min())) - 1, 0)
    r1 = min(int(np.searchsorted(ys, y.max())) + 1, hs)
    if c0 >= c1 or r0 >= r1:
        return None
    return slice(r0, r1), slice(c0, c1)


def _cast(scene: SyntheticScene, T_wc: np.ndarray,
          dirs_c: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Nearest hit along each ray of a grid. dirs_c: [Hs, Ws, 3] camera-frame rays with z = 1.

    Returns (t [Hs, Ws] = camera z of the hit, surface index [Hs, Ws] int32 (room faces 0-5,
    box b faces 6+6b..), hit point components [x, y, z] each [Hs, Ws]), float32.
    """
    R = T_wc[:3, :3].astype(np.float32)
    o = T_wc[:3, 3].astype(np.float32)
    T_cw = np.linalg.inv(T_wc)
    # per-component planes: numpy reductions over a trailing axis of 3 are slow, so never make them
    d = [dirs_c @ R[k] for k in range(3)]  # world directions; t along them equals camera z
    d = [np.where(np.abs(dk) < 1e-9, np.float32(1e-9), dk) for dk in d]
    inv = [np.float32(1.0) / dk for dk in d]
    lo, hi = scene.room_lo.astype(np.float32), scene.room_hi.astype(np.float32)
    pos = [dk > 0 for dk in d]
    # exit of the room box from inside: per axis the face the ray points at
    t = sid = None
    for k in range(3):
        tk = (np.where(pos[k], hi[k], lo[k]) - o[k]) * inv[k]
        sk = (2 * k + pos[k]).astype(np.int32)
        if t is None:
            t, sid = tk, sk
        else:
            closer = tk < t
            t = np.where(closer, tk, t)
            sid = np.where(closer, sk, sid)
    assert t is not None and sid is not None
    for b in range(len(scene.boxes_lo)):
        blo, bhi = scene.boxes_lo[b], scene.boxes_hi[b]
        win = _box_window(blo, bhi, T_cw, dirs_c)
        if win is None:
            continue
        blo32, bhi32 = blo.astype(np.float32), bhi.astype(np.float32)
        slabs = []
        for k in range(3):
            pk, ik = pos[k][win], inv[k][win]
            t1 = (blo32[k] - o[k]) * ik
            t2 = (bhi32[k] - o[k]) * ik
            # a ray going +axis enters through the lo face (side 0)
            side = np.where(pk, np.int32(2 * k), np.int32(2 * k + 1))
            slabs.append((np.where(pk, t1, t2), np.where(pk, t2, t1), side))
        tnear, tfar, face = slabs[0]
        for tmin, tmax, side in slabs[1:]:
            later = tmin > tnear
            tnear = np.where(later, tmin, tnear)
            face = np.where(later, side, face)
            tfar = np.minimum(tfar, tmax)
        tw = t[win]
        hit = (tnear <= tfar) & (tnear > 0) & (tnear < tw)
        t[win] = np.where(hit, tnear, tw)
        sid[win] = np.where(hit, face + np.int32(6 + 6 * b), sid[win])
    p = [o[k] + d[k] * t for k in range(3)]
    return t, sid, p


def render(scene: SyntheticScene, camera: PinholeCamera, T_wc: np.ndarray,
           aa: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Render one view (pinhole, distortion ignored).

    T_wc: [4, 4] camera-to-world (optical frame: x right, y down, z forward).
    aa: colour rays per pixel per axis (box-filtered); depth always uses pixel centres.
    Returns (rgb [H, W, 3] uint8, depth_m [H, W] float32, exact z at pixel centres).
    """
    t, sid, p = _cast(scene, T_wc, _ray_dirs(camera, 1))
    depth = t.astype(np.float32)
    if aa > 1:
        _, sid, p = _cast(scene, T_wc, _ray_dirs(camera, aa))
    # per face an affine map world point -> atlas pixel: texel c's centre is at (c + 0.5) * TEXEL
    S = scene.surfaces
    ua = np.array([s.u_axis for s in S]) / TEXEL_M
    va = np.array([s.v_axis for s in S]) / TEXEL_M
    orig = np.array([s.origin for s in S])
    off = np.array([s.atlas_xy for s in S], np.float64)
    bu = off[:, 0] - 0.5 - np.einsum("sk,sk->s", orig, ua)
    bv = off[:, 1] - 0.5 - np.einsum("sk,sk->s", orig, va)
    # float error puts a hit at most ~1e-6 m off its face; the atlas gutter (2 texels) absorbs it
    mx = np.take(bu.astype(np.float32), sid)
    my = np.take(bv.astype(np.float32), sid)
    for k in range(3):
        mx += np.take(ua[:, k].astype(np.float32), sid) * p[k]
        my += np.take(va[:, k].astype(np.float32), sid) * p[k]
    rgb = cv2.remap(scene.atlas, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if aa > 1:
        rgb = cv2.resize(rgb, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    return rgb, depth


# ------------------------------------------------------------------------- trajectory


def _look_pose(position: np.ndarray, yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Camera-to-world pose [4, 4] of an optical frame looking along (yaw, pitch), rolled about its view axis."""
    f = np.array([math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), math.sin(pitch)])
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    c, s = math.cos(roll), math.sin(roll)
    x_c, y_c = c * right + s * down, -s * right + c * down
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x_c, y_c, f, position
    return T


LOOP_OVERLAP = 0.12  # fraction of the round the loop path retraces after coming back to its start
_LOOP_CENTRE = (-0.2, 0.0)  # ellipse round the room's free floor (boxes stay outside or below)
_LOOP_RADII = (1.9, 1.3)


def loop_revisit_frames(spec: SyntheticSpec) -> np.ndarray:
    """Indices [K] of the frames of a ``path=loop`` sequence that revisit the start (after one round)."""
    if spec.path != "loop":
        return np.zeros(0, np.int64)
    s = _loop_phase(spec.n_frames)
    return np.flatnonzero(s >= 1.0)


def _loop_phase(n: int) -> np.ndarray:
    """Phase [n] of each frame along the loop: 0 .. 1 + LOOP_OVERLAP (1 = back at the start)."""
    return np.arange(n) / max(n - 1, 1) * (1.0 + LOOP_OVERLAP)


def _loop_trajectory(spec: SyntheticSpec) -> np.ndarray:
    """T_wc [N, 4, 4] of the loop path: an ellipse round the room at 1.35 m, looking outwards
    (yaw = polar angle + 135 deg: inwards and ahead), small seeded height/pitch/roll wobble."""
    return _round_trajectory(spec, _loop_phase(spec.n_frames))


def _round_trajectory(spec: SyntheticSpec, s: np.ndarray) -> np.ndarray:
    """T_wc [N, 4, 4] at phases ``s`` [N] of the round (1 = once round): the loop and orbit paths."""
    rng = np.random.default_rng([spec.seed, 4])
    ph = rng.uniform(0, 2 * np.pi, 3)
    a, r = spec.path_amp, spec.path_rot * np.pi / 180
    poses = np.empty((len(s), 4, 4))
    for k, sk in enumerate(s.tolist()):
        th = 2 * np.pi * sk
        pos = np.array([_LOOP_CENTRE[0] + _LOOP_RADII[0] * math.cos(th),
                        _LOOP_CENTRE[1] + _LOOP_RADII[1] * math.sin(th),
                        1.35 + a * 0.05 * math.sin(3 * th + ph[0])])
        yaw = th + 0.75 * np.pi
        pitch = -15 * np.pi / 180 + 4 * r * math.sin(2 * th + ph[1])
        roll = 4 * r * math.sin(3 * th + ph[2])
        poses[k] = _look_pose(pos, yaw, pitch, roll)
    return poses


def trajectory(spec: SyntheticSpec) -> tuple[np.ndarray, np.ndarray]:
    """The camera path: (stamps_ns [N] int64, T_wc [N, 4, 4] float64), N = ``total_frames``: one lap
    of ``n_frames`` poses, flown ``laps`` times (frame k has frame k % n_frames's pose)."""
    stamps = SYNTH_START_NS + np.round(np.arange(spec.total_frames) * 1e6 / spec.fps).astype(np.int64) * 1000
    lap = _lap_poses(spec)
    return stamps, np.tile(lap, (spec.laps, 1, 1)) if spec.laps > 1 else lap


def _lap_poses(spec: SyntheticSpec) -> np.ndarray:
    """T_wc [n_frames, 4, 4] of one lap.

    ``path=wobble`` (default): one smooth closed loop over the sequence (so total travel does not depend on n):
    position an ellipse-like loop around (-1.3, 0, 1.35) with a vertical wobble, yaw +-35 deg
    around +x, pitch -12 +- 8 deg, roll +-8 deg, phases seeded. Stamps are whole microseconds
    so TUM text files round-trip exactly. ``path=loop``: see ``_loop_trajectory``; ``path=orbit``:
    the loop's round at phases k / n_frames (closed: a next lap goes on without a jump).
    """
    if spec.path == "loop":
        return _loop_trajectory(spec)
    if spec.path == "orbit":
        return _round_trajectory(spec, np.arange(spec.n_frames) / spec.n_frames)
    rng = np.random.default_rng([spec.seed, 2])
    ph = rng.uniform(0, 2 * np.pi, 6)
    n = spec.n_frames
    s = np.arange(n) / max(n, 1)
    two_pi = 2 * np.pi
    a, r = spec.path_amp, spec.path_rot * np.pi / 180
    poses = np.empty((n, 4, 4))
    for k in range(n):
        pos = np.array([-1.3 + a * 0.25 * math.sin(two_pi * s[k] + ph[0]),
                        a * 0.35 * math.sin(two_pi * s[k] + ph[1]),
                        1.35 + a * 0.08 * math.sin(2 * two_pi * s[k] + ph[2])])
        yaw = 35 * r * math.sin(two_pi * s[k] + ph[3])
        pitch = -12 * np.pi / 180 + 8 * r * math.sin(2 * two_pi * s[k] + ph[4])
        roll = 8 * r * math.sin(two_pi * s[k] + ph[5])
        poses[k] = _look_pose(pos, yaw, pitch, roll)
    return poses


def _corrupt_depth(depth: np.ndarray, spec: SyntheticSpec, index: int) -> np.ndarray:
    """Add Gaussian noise and zero-valued hole blobs, deterministic in (seed, frame index)."""
    rng = np.random.default_rng([spec.seed, 3, index])
    out = depth
    if spec.depth_noise_std_m > 0:
        out = out + rng.normal(0.0, spec.depth_noise_std_m, out.shape).astype(np.float32)
        out = np.maximum(out, np.float32(1e-3))
    if spec.hole_fraction > 0:
        h, w = out.shape
        coarse = rng.random((max(2, h // 12), max(2, w // 12)), dtype=np.float32)
        field = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
        thr = np.quantile(field, 1.0 - spec.hole_fraction)
        out = np.where(field > thr, np.float32(0.0), out)
    return out.astype(np.float32, copy=False)


def generate_frames(spec: SyntheticSpec, scene: SyntheticScene | None = None) -> Iterator[Frame]:
    """Frames of the synthetic sequence with exact ground truth T_wc_gt and depth (float32 m).

    Deterministic: the same spec gives the same bytes. The scene is built lazily on the
    first frame (pass ``scene`` to reuse one across calls; it must come from ``build_scene(spec.seed)``).
    With ``laps`` > 1 the first lap's images are kept and shown again on every later lap (restamped:
    a lap's frame k is the same view every time round), so a long flight renders one lap.
    """
    stamps, poses = trajectory(spec)
    camera = spec.camera
    if scene is None:
        scene = build_scene(spec.seed)
    elif scene.seed != spec.seed:
        raise ConfigError(f"scene was built with seed {scene.seed}, the spec has seed {spec.seed}")
    lap: list[Frame] = []
    for k in range(spec.n_frames):
        rgb, depth = render(scene, camera, poses[k], spec.aa)
        depth = _corrupt_depth(depth, spec, k)
        frame = Frame(int(stamps[k]), rgb, depth, camera, poses[k].copy())
        if spec.laps > 1:
            lap.append(frame)
        yield frame
    for k in range(spec.n_frames, spec.total_frames):
        yield replace(lap[k % spec.n_frames], stamp_ns=int(stamps[k]))


# --------------------------------------------------------------------- TUM folder out


def write_tum_folder(frames: Iterable[Frame], path: str | os.PathLike[str], depth_factor: float = 5000.0) -> int:
    """Write frames as a TUM RGB-D folder (rgb/, depth/ 16-bit PNG, rgb.txt, depth.txt, groundtruth.txt).

    Written into a temporary sibling directory and renamed into place, so ``path`` is
    either complete or absent. Depth NaN/0/out of range -> 0. Stamps are written in whole
    microseconds (TUM's format). The camera of the first frame and the depth factor go to
    ``camera.json`` (read back by ``TumFolder``). Returns the number of frames.
    """
    out = Path(path)
    if out.exists():
        raise DataError(f"{out}: already exists; refusing to overwrite a dataset folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        (tmp / "rgb").mkdir()
        (tmp / "depth").mkdir()
        rgb_lines = ["# color images", "# file: memgs_ros synthetic", "# timestamp filename"]
        depth_lines = ["# depth maps", "# file: memgs_ros synthetic", "# timestamp filename"]
        gt_lines = ["# ground truth trajectory", "# file: memgs_ros synthetic", "# timestamp tx ty tz qx qy qz qw"]
        n = 0
        for f in frames:
            ts = format_stamp(f.stamp_ns)
            if n == 0:
                write_camera_json(tmp / CAMERA_JSON, f.camera, depth_factor)
            if not cv2.imwrite(str(tmp / "rgb" / f"{ts}.png"), cv2.cvtColor(f.rgb, cv2.COLOR_RGB2BGR)):
                raise DataError(f"{tmp / 'rgb' / ts}.png: could not write image")
            rgb_lines.append(f"{ts} rgb/{ts}.png")
            if (depth_m := f.depth_metres()) is not None:
                d = metres_to_depth_units(depth_m, depth_factor)
                if not cv2.imwrite(str(tmp / "depth" / f"{ts}.png"), d):
                    raise DataError(f"{tmp / 'depth' / ts}.png: could not write depth image")
                depth_lines.append(f"{ts} depth/{ts}.png")
            if f.T_wc_gt is not None:
                gt_lines.append(format_pose_line(ts, f.T_wc_gt))
            n += 1
        for name, lines in (("rgb.txt", rgb_lines), ("depth.txt", depth_lines), ("groundtruth.txt", gt_lines)):
            (tmp / name).write_text("\n".join(lines) + "\n")
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return n


__all__ = [
    "SYNTH_START_NS",
    "SyntheticScene",
    "SyntheticSpec",
    "build_scene",
    "generate_frames",
    "is_spec_string",
    "loop_revisit_frames",
    "parse_spec",
    "render",
    "trajectory",
    "write_tum_folder",
]
