"""The synthetic room as a scene: geometry (6 x 5 x 2.7 m room, six boxes) and one texture atlas
baked per seed (procedural textures in surface coordinates, 5 mm texels). Rendering, camera
paths and frames are :mod:`memgs_ros.io.synthetic`.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

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


