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
holes (fraction of depth pixels zeroed in random blobs), path (wobble or loop), amp (path translation scale,
1 = about 1.9 m of travel), rot (path rotation scale, 1 = yaw +-35 deg, pitch +-8 deg,
roll +-8 deg), aa (colour supersampling factor; 0 = auto: 2 up to 320x240, else 1).
Defaults: 640x480, 120 frames at 30 fps, seed 0, no noise, no holes, path=wobble.

``path=loop`` is a loop-closure sequence: the camera goes once round the room (about 10 m,
looking out at the walls and furniture) and then retraces the first ``LOOP_OVERLAP`` of the
round, so the last frames revisit the start views (``loop_revisit_frames``).

The room geometry (6 x 5 x 2.7 m, six boxes) is fixed; the seed changes the textures and
the phases of the camera path. The camera is TUM fr3-like without distortion, scaled to
the image size; stamps start at SYNTH_START_NS and are whole microseconds.
"""
from __future__ import annotations

import math
import os
import shutil
import tempfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, fields
from pathlib import Path

import cv2
import numpy as np

from memgs_ros.core.camera import TUM_FR3, PinholeCamera
from memgs_ros.core.frame import Frame
from memgs_ros.core.geometry import pose_to_tq
from memgs_ros.errors import ConfigError, DataError
from memgs_ros.io.tum import CAMERA_JSON, format_stamp, write_camera_json

# Synthetic stamps start here (a plausible wall-clock epoch, like TUM's), in ns.
SYNTH_START_NS = 1_700_000_000 * 1_000_000_000
TEXEL_M = 0.005  # atlas resolution on every surface
ROOM_LO = (-3.0, -2.5, 0.0)  # metres, world frame, z up
ROOM_HI = (3.0, 2.5, 2.7)
# Boxes on (or near) the floor: (lo xyz, hi xyz). The camera path stays at x < -0.6.
BOXES: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = (
    ((0.6, -0.9, 0.0), (1.4, -0.1, 0.8)),
    ((1.6, 0.4, 0.0), (2.5, 1.5, 1.1)),
    ((0.9, 0.9, 0.0), (1.3, 1.3, 0.4)),
    ((2.0, -2.2, 0.0), (2.9, -1.2, 1.6)),
    ((1.0, -0.7, 0.8), (1.25, -0.35, 1.15)),  # a small box on top of the first one
    ((-1.5, 1.9, 0.0), (0.2, 2.5, 0.9)),  # a sideboard against the +y wall
)
SPEC_KEYS = {
    "w": "width", "h": "height", "n": "n_frames", "fps": "fps", "seed": "seed",
    "noise": "depth_noise_std_m", "holes": "hole_fraction", "amp": "path_amp", "rot": "path_rot",
    "aa": "supersample", "path": "path",
}
PATH_KINDS = ("wobble", "loop")


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
        if not 0 <= self.supersample <= 4:
            raise ConfigError(f"synthetic supersample must be 0 (auto) .. 4, got {self.supersample}")

    @property
    def camera(self) -> PinholeCamera:
        sx, sy = self.width / TUM_FR3.width, self.height / TUM_FR3.height
        return PinholeCamera(self.width, self.height, TUM_FR3.fx * sx, TUM_FR3.fy * sy,
                             (TUM_FR3.cx + 0.5) * sx - 0.5, (TUM_FR3.cy + 0.5) * sy - 0.5)

    @property
    def aa(self) -> int:
        if self.supersample:
            return self.supersample
        return 2 if self.width * self.height <= 320 * 240 else 1

    def to_string(self) -> str:
        """The spec string that ``parse_spec`` turns back into this spec."""
        # path only when not the default, so default specs keep their old names
        parts = [f"{k}={getattr(self, f)}" for k, f in SPEC_KEYS.items() if k != "path" or self.path != "wobble"]
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


# ----------------------------------------------------------------------------- scene


@dataclass(frozen=True)
class Surface:
    """One textured planar face. A point p on it has texture coords ((p-origin).u_axis, (p-origin).v_axis) m."""

    name: str
    normal: np.ndarray  # [3] unit, pointing into free space
    origin: np.ndarray  # [3]
    u_axis: np.ndarray  # [3] unit
    v_axis: np.ndarray  # [3] unit
    size_m: tuple[float, float]  # extent along u, v
    atlas_xy: tuple[int, int]  # texel offset of (0, 0) in the atlas

    @property
    def plane_d(self) -> float:
        """Plane normal . p = plane_d for points on the surface."""
        return float(self.normal @ self.origin)


@dataclass(frozen=True)
class SyntheticScene:
    """The room: boxes, the faces (room faces first: 6, then 6 per box) and the baked atlas."""

    seed: int
    room_lo: np.ndarray  # [3]
    room_hi: np.ndarray  # [3]
    boxes_lo: np.ndarray  # [B, 3]
    boxes_hi: np.ndarray  # [B, 3]
    surfaces: tuple[Surface, ...]
    atlas: np.ndarray  # [Ha, Wa, 3] uint8 RGB


def _face_frames(lo: np.ndarray, hi: np.ndarray, inward: bool
                 ) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[float, float]]]:
    """Six faces of an AABB as (name, normal, origin, u_axis, v_axis, size); face index = 2*axis + (0 lo, 1 hi).

    Walls get v up (z); floor/ceiling and box tops get u = x, v = y.
    """
    out = []
    e = np.eye(3)
    for axis in range(3):
        for side in range(2):
            coord = (lo if side == 0 else hi)[axis]
            outward = e[axis] * (-1.0 if side == 0 else 1.0)
            normal = -outward if inward else outward
            if axis == 2:
                u, v = e[0], e[1]
            else:
                u, v = e[1 - axis], e[2]
            origin = lo.copy()
            origin[axis] = coord
            size = (float(hi @ u - lo @ u), float(hi @ v - lo @ v))
            name = f"{'xyz'[axis]}{'-+'[side]}"
            out.append((name, normal, origin, u, v, size))
    return out


class _Noise:
    """Seeded 2D value noise (smooth, band-limited): lattice of random values, smoothstep-bilinear."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.table = rng.random((256, 256), dtype=np.float32)

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """x, y: [...] float lattice coordinates -> [...] values in [0, 1]."""
        xf, yf = np.floor(x), np.floor(y)
        fx, fy = (x - xf).astype(np.float32), (y - yf).astype(np.float32)
        fx = fx * fx * (3 - 2 * fx)
        fy = fy * fy * (3 - 2 * fy)
        ix, iy = xf.astype(np.int64) & 255, yf.astype(np.int64) & 255
        t = self.table
        a, b = t[iy, ix], t[iy, (ix + 1) & 255]
        c, d = t[(iy + 1) & 255, ix], t[(iy + 1) & 255, (ix + 1) & 255]
        return (a + (b - a) * fx) + ((c + (d - c) * fx) - (a + (b - a) * fx)) * fy

    def fbm(self, x: np.ndarray, y: np.ndarray, octaves: int = 2) -> np.ndarray:
        out = np.zeros(np.broadcast(x, y).shape, np.float32)
        amp, norm = 1.0, 0.0
        for o in range(octaves):
            out += amp * self(x * 2**o + 17.3 * o, y * 2**o + 5.1 * o)
            norm += amp
            amp *= 0.5
        return out / norm


def _smooth_field(fn: Callable[[np.ndarray, np.ndarray], np.ndarray], w: int, h: int, step: int = 8) -> np.ndarray:
    """Evaluate a smooth field fn(u_m, v_m) on every ``step``-th texel and upsample bilinearly to [h, w].

    Only for fields that vary over decimetres (blotches, light falloff): 8 texels = 4 cm.
    """
    cw, ch = w // step + 2, h // step + 2
    u = (np.arange(cw, dtype=np.float32) * step + 0.5) * TEXEL_M
    v = (np.arange(ch, dtype=np.float32) * step + 0.5) * TEXEL_M
    coarse = np.ascontiguousarray(fn(u[None, :].repeat(ch, 0), v[:, None].repeat(cw, 1)), dtype=np.float32)
    # coarse sample k sits on texel k*step; map texel c to coarse coordinate c/step
    xs = (np.arange(w, dtype=np.float32) / step)[None, :].repeat(h, 0)
    ys = (np.arange(h, dtype=np.float32) / step)[:, None].repeat(w, 1)
    return cv2.remap(coarse, xs, ys, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _rect(u: np.ndarray, v: np.ndarray, u0: float, v0: float, u1: float, v1: float) -> np.ndarray:
    return (u >= u0) & (u < u1) & (v >= v0) & (v < v1)


def _poster(img: np.ndarray, u: np.ndarray, v: np.ndarray, rect: tuple[float, float, float, float],
            kind: int, rng: np.random.Generator, noise: _Noise) -> None:
    """Paint a framed poster of one of four designs into img [h, w, 3] (in place)."""
    u0, v0, u1, v1 = rect
    inside = _rect(u, v, u0, v0, u1, v1)
    img[inside] = (0.08, 0.08, 0.1)  # frame
    b = 0.02
    inner = _rect(u, v, u0 + b, v0 + b, u1 - b, v1 - b)
    pu, pv = (u - u0 - b)[inner], (v - v0 - b)[inner]
    pal = rng.random((8, 3)).astype(np.float32) * 0.8 + 0.1
    if kind == 0:  # grid of coloured cells
        nu, nv = int(rng.integers(3, 6)), int(rng.integers(3, 6))
        cu = np.minimum((pu / ((u1 - u0 - 2 * b) / nu)).astype(int), nu - 1)
        cv = np.minimum((pv / ((v1 - v0 - 2 * b) / nv)).astype(int), nv - 1)
        cell = rng.integers(0, 8, size=(nv, nu))
        col = pal[cell[cv, cu]]
    elif kind == 1:  # concentric rings
        cu, cv = (u1 - u0) / 2 - b, (v1 - v0) / 2 - b
        r = np.hypot(pu - cu, pv - cv)
        ring = (r / 0.06).astype(int) % 4
        col = pal[ring]
    elif kind == 2:  # diagonal stripes over a two-tone split
        s = ((pu + pv) / 0.07).astype(int) % 2
        half = (pv > (v1 - v0) / 2).astype(int) * 2
        col = pal[s + half]
    else:  # posterised smooth "landscape"
        n = noise.fbm(pu / 0.12 + rng.random() * 50, pv / 0.12 + rng.random() * 50, octaves=2)
        level = np.clip((n * 5).astype(int), 0, 4)
        col = pal[level]
    img[inner] = col


def _bake_texture(name: str, kind: str, size_m: tuple[float, float], rng: np.random.Generator,
                  noise: _Noise, base: np.ndarray) -> np.ndarray:
    """Texture [h, w, 3] float32 in [0, 1] of one face; texel (row r, col c) is at v=(r+.5)*TEXEL, u=(c+.5)*TEXEL."""
    w = max(2, math.ceil(size_m[0] / TEXEL_M))
    h = max(2, math.ceil(size_m[1] / TEXEL_M))
    u = ((np.arange(w, dtype=np.float32) + 0.5) * TEXEL_M)[None, :].repeat(h, 0)
    v = ((np.arange(h, dtype=np.float32) + 0.5) * TEXEL_M)[:, None].repeat(w, 1)
    ou, ov = rng.random() * 100, rng.random() * 100
    blot = _smooth_field(lambda uu, vv: noise.fbm(uu / 0.45 + ou, vv / 0.45 + ov, octaves=2), w, h)
    img = np.empty((h, w, 3), np.float32)
    img[:] = base
    if kind == "floor":
        tile = 0.5
        tu, tv = np.floor(u / tile).astype(int), np.floor(v / tile).astype(int)
        tint = rng.random((64, 64)).astype(np.float32)[tv % 64, tu % 64]
        img *= (0.8 + 0.3 * tint)[..., None]
        grout = ((u % tile) < 0.012) | ((v % tile) < 0.012)
        img[grout] = (0.25, 0.23, 0.2)
        # a striped rug in the middle of the room
        ru0, rv0 = size_m[0] * 0.3, size_m[1] * 0.3
        ru1, rv1 = size_m[0] * 0.62, size_m[1] * 0.7
        rug = _rect(u, v, ru0, rv0, ru1, rv1)
        border = rug & ~_rect(u, v, ru0 + 0.1, rv0 + 0.1, ru1 - 0.1, rv1 - 0.1)
        stripes = ((u - ru0) / 0.15).astype(int) % 3
        rug_pal = np.array([(0.6, 0.15, 0.12), (0.85, 0.7, 0.4), (0.15, 0.25, 0.5)], np.float32)
        img[rug] = rug_pal[stripes[rug]]
        img[border] = (0.1, 0.12, 0.3)
    elif kind == "ceiling":
        panel = 0.6
        lines = ((u % panel) < 0.015) | ((v % panel) < 0.015)
        img[lines] = base * 0.7
        for cu, cv in ((0.35, 0.35), (0.65, 0.35), (0.35, 0.7), (0.65, 0.7)):
            lamp = _rect(u, v, size_m[0] * cu - 0.3, size_m[1] * cv - 0.15, size_m[0] * cu + 0.3, size_m[1] * cv + 0.15)
            img[lamp] = (1.0, 0.98, 0.9)
    elif kind == "wall":
        img[v < 0.1] = (0.3, 0.25, 0.2)  # skirting board
        img[(v > 0.9) & (v < 0.94)] = base * 0.6  # dado rail
        lo_u, hi_u = 0.2, size_m[0] - 0.2
        if name == "x+":  # door
            img[_rect(u, v, 3.6, 0.0, 4.5, 2.05)] = (0.45, 0.3, 0.18)
            img[_rect(u, v, 3.65, 0.05, 4.45, 2.0)] = (0.55, 0.38, 0.22)
            img[_rect(u, v, 3.7, 0.95, 3.8, 1.0)] = (0.8, 0.75, 0.5)
            hi_u = 3.4
        if name == "y+":  # window with a cross bar
            img[_rect(u, v, 3.5, 1.0, 5.0, 2.2)] = (0.9, 0.9, 0.85)
            img[_rect(u, v, 3.55, 1.05, 4.22, 1.57)] = (0.55, 0.75, 0.95)
            img[_rect(u, v, 4.28, 1.05, 4.95, 1.57)] = (0.55, 0.75, 0.95)
            img[_rect(u, v, 3.55, 1.63, 4.22, 2.15)] = (0.6, 0.8, 0.97)
            img[_rect(u, v, 4.28, 1.63, 4.95, 2.15)] = (0.6, 0.8, 0.97)
            hi_u = 3.3
        # posters in slots along the wall, sizes and heights seeded
        n_slots = max(1, int((hi_u - lo_u) / 1.1))
        slot = (hi_u - lo_u) / n_slots
        for k in range(n_slots):
            pw, ph = rng.uniform(0.45, min(0.9, slot - 0.15)), rng.uniform(0.4, 0.75)
            pu0 = lo_u + k * slot + rng.uniform(0.05, slot - pw - 0.05)
            pv0 = rng.uniform(1.05, 2.45 - ph)
            _poster(img, u, v, (pu0, pv0, pu0 + pw, pv0 + ph), int(rng.integers(0, 4)), rng, noise)
    elif kind == "box":
        s = int(rng.integers(0, 3))
        if s == 0:
            img[((v / 0.08).astype(int) % 2) == 0] = base * 0.55
        elif s == 1:
            img[((np.floor(u / 0.1) + np.floor(v / 0.1)) % 2) == 0] = base * 0.6
        label = _rect(u, v, size_m[0] * 0.2, size_m[1] * 0.3, size_m[0] * 0.8, size_m[1] * 0.6)
        img[label] = (0.92, 0.9, 0.85)
        img[label & (((u / 0.05).astype(int) % 3) == 0) & (v < size_m[1] * 0.5)] = (0.1, 0.1, 0.1)
    img *= (0.85 + 0.25 * blot)[..., None]
    return img


def build_scene(seed: int = 0) -> SyntheticScene:
    """Build the room and bake its texture atlas; deterministic in ``seed`` (~0.5 s)."""
    rng = np.random.default_rng([seed, 1])
    noise = _Noise(rng)
    room_lo, room_hi = np.array(ROOM_LO), np.array(ROOM_HI)
    boxes_lo = np.array([b[0] for b in BOXES], dtype=np.float64)
    boxes_hi = np.array([b[1] for b in BOXES], dtype=np.float64)
    wall_pal = np.array([(0.85, 0.8, 0.7), (0.7, 0.78, 0.85), (0.82, 0.72, 0.68), (0.74, 0.82, 0.72)], np.float32)
    box_pal = np.array([(0.8, 0.3, 0.2), (0.2, 0.5, 0.8), (0.9, 0.75, 0.2), (0.3, 0.65, 0.35),
                        (0.65, 0.3, 0.65), (0.55, 0.4, 0.25)], np.float32)
    light = np.array([0.0, 0.0, 2.6])  # soft ceiling light for baked shading
    faces: list[tuple[str, str, np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[float, float], np.ndarray]] = []
    for i, (name, n, o, ua, va, size) in enumerate(_face_frames(room_lo, room_hi, inward=True)):
        kind = "floor" if name == "z-" else "ceiling" if name == "z+" else "wall"
        base = {"floor": np.array((0.62, 0.5, 0.36), np.float32),
                "ceiling": np.array((0.9, 0.9, 0.88), np.float32)}.get(
            kind, wall_pal[i % 4] * (0.9 + 0.2 * rng.random(3).astype(np.float32)))
        faces.append((name, kind, n, o, ua, va, size, base))
    for b in range(len(boxes_lo)):
        base = box_pal[b % len(box_pal)] * (0.85 + 0.3 * rng.random(3).astype(np.float32))
        for name, n, o, ua, va, size in _face_frames(boxes_lo[b], boxes_hi[b], inward=False):
            faces.append((f"box{b}{name}", "box", n, o, ua, va, size, base))
    textures = []
    for name, kind, n, o, ua, va, size, base in faces:
        tex = _bake_texture(name, kind, size, rng, noise, base)
        # baked shading: orientation term + soft falloff from the light (view-independent)
        h, w = tex.shape[:2]
        rel = (o - light).astype(np.float32)
        ua32, va32 = ua.astype(np.float32), va.astype(np.float32)

        def falloff(uu: np.ndarray, vv: np.ndarray, rel: np.ndarray = rel, ua32: np.ndarray = ua32,
                    va32: np.ndarray = va32) -> np.ndarray:
            # squared distance from the light of the surface point at (uu, vv)
            dist2 = sum((rel[k] + uu * ua32[k] + vv * va32[k]) ** 2 for k in range(3))
            return np.exp(-dist2 / np.float32(12.0))

        orient = 0.8 + 0.2 * float(n @ np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]))
        shade = (orient * (0.7 + 0.45 * _smooth_field(falloff, w, h))).astype(np.float32)
        textures.append(np.clip(tex * shade[..., None], 0.0, 1.0))
    # shelf-pack the textures into one atlas with a 2-texel gutter (bilinear never bleeds)
    atlas_w, gutter = 2048, 2
    x = y = shelf_h = 0
    offsets = []
    for tex in textures:
        h, w = tex.shape[:2]
        if x + w + gutter > atlas_w:
            x, y, shelf_h = 0, y + shelf_h, 0
        offsets.append((x + gutter, y + gutter))
        x += w + 2 * gutter
        shelf_h = max(shelf_h, h + 2 * gutter)
    atlas = np.zeros((y + shelf_h, atlas_w, 3), np.uint8)
    surfaces = []
    for (name, _kind, n, o, ua, va, size, _base), tex, (ox, oy) in zip(faces, textures, offsets):
        h, w = tex.shape[:2]
        # edge-replicate into the gutter so bilinear taps at a face's border stay on that face's colour
        atlas[oy - gutter:oy + h + gutter, ox - gutter:ox + w + gutter] = np.pad(
            np.round(tex * 255).astype(np.uint8), ((gutter, gutter), (gutter, gutter), (0, 0)), mode="edge")
        surfaces.append(Surface(name, n.astype(np.float64), o.astype(np.float64), ua.astype(np.float64),
                                va.astype(np.float64), size, (ox, oy)))
    return SyntheticScene(seed, room_lo, room_hi, boxes_lo, boxes_hi, tuple(surfaces), atlas)


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
        tnear = tfar = face = None
        for k in range(3):
            pk, ik = pos[k][win], inv[k][win]
            t1 = (blo32[k] - o[k]) * ik
            t2 = (bhi32[k] - o[k]) * ik
            # a ray going +axis enters through the lo face (side 0)
            tmin, tmax = np.where(pk, t1, t2), np.where(pk, t2, t1)
            if tnear is None:
                tnear, tfar, face = tmin, tmax, np.where(pk, np.int32(2 * k), np.int32(2 * k + 1))
            else:
                later = tmin > tnear
                tnear = np.where(later, tmin, tnear)
                face = np.where(later, np.where(pk, np.int32(2 * k), np.int32(2 * k + 1)), face)
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
    rng = np.random.default_rng([spec.seed, 4])
    ph = rng.uniform(0, 2 * np.pi, 3)
    s = _loop_phase(spec.n_frames)
    a, r = spec.path_amp, spec.path_rot * np.pi / 180
    poses = np.empty((spec.n_frames, 4, 4))
    for k, sk in enumerate(s):
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
    """The camera path: (stamps_ns [N] int64, T_wc [N, 4, 4] float64).

    ``path=wobble`` (default): one smooth closed loop over the sequence (so total travel does not depend on n):
    position an ellipse-like loop around (-1.3, 0, 1.35) with a vertical wobble, yaw +-35 deg
    around +x, pitch -12 +- 8 deg, roll +-8 deg, phases seeded. Stamps are whole microseconds
    so TUM text files round-trip exactly. ``path=loop``: see ``_loop_trajectory``.
    """
    stamps = SYNTH_START_NS + np.round(np.arange(spec.n_frames) * 1e6 / spec.fps).astype(np.int64) * 1000
    if spec.path == "loop":
        return stamps, _loop_trajectory(spec)
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
    return stamps, poses


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
    """
    stamps, poses = trajectory(spec)
    camera = spec.camera
    if scene is None:
        scene = build_scene(spec.seed)
    elif scene.seed != spec.seed:
        raise ConfigError(f"scene was built with seed {scene.seed}, the spec has seed {spec.seed}")
    for k in range(spec.n_frames):
        rgb, depth = render(scene, camera, poses[k], spec.aa)
        depth = _corrupt_depth(depth, spec, k)
        yield Frame(int(stamps[k]), rgb, depth, camera, poses[k].copy())


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
            if f.depth_m is not None:
                d = np.nan_to_num(f.depth_m.astype(np.float64), nan=0.0) * depth_factor
                d = np.where((d > 0) & (d < 65535.5), np.round(d), 0).astype(np.uint16)
                if not cv2.imwrite(str(tmp / "depth" / f"{ts}.png"), d):
                    raise DataError(f"{tmp / 'depth' / ts}.png: could not write depth image")
                depth_lines.append(f"{ts} depth/{ts}.png")
            if f.T_wc_gt is not None:
                t, q = pose_to_tq(f.T_wc_gt)
                gt_lines.append(f"{ts} " + " ".join(f"{x:.9f}" for x in (*t, *q)))
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
    "Surface",
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
