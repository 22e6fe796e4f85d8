"""Map bundles: one folder per saved map, so a later flight can continue it or localise in it.

A bundle holds:

- ``map.ply`` (+ ``map.ply.ids.npy``): the Gaussian map, the standard 3DGS PLY, and its ids;
- ``tracker.npz``: the tracker's map (``core/tracking/map_io.py``: keyframes with poses, ORB
  keypoints and descriptors, bag-of-words vectors, map points; covisibility follows from them);
- ``mapper.npz``: what the mapper continues from (a mapper checkpoint: the Gaussians with their
  training bookkeeping, every keyframe view it trains on, exposure);
- ``manifest.json``: format version, camera, tracker mode, depth units, SH degree, map frame,
  frames, keyframes, Gaussians, source, created, and each file's size and SHA-256.

Written atomically: the files go into a hidden staging folder beside the bundles, the manifest
last, then one rename gives the bundle its name (a new one each save: never over an existing
bundle) and ``latest`` (a symlink) is replaced to point at it. A save killed half-way leaves the
previous bundles and ``latest`` as they were, and a staging folder that nothing loads (no
manifest, or a hidden name; the next save removes it). Loading checks the manifest and every
file's size and hash before any node starts, and refuses with one line naming what is wrong.

No ROS here; the nodes write their parts and the merger assembles them (``nodes/merger/bundles.py``).
"""
from __future__ import annotations

import contextlib
import datetime as dt
import hashlib
import json
import os
import secrets
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from memgs_ros.core.runtime.atomic import atomic_write
from memgs_ros.errors import DataError

__all__ = [
    "BUNDLE_FORMAT",
    "LATEST",
    "MANIFEST",
    "MAPPER_FILE",
    "PLY_FILE",
    "TRACKER_FILE",
    "BundleError",
    "Manifest",
    "check_bundle",
    "commit_bundle",
    "discard_staging",
    "new_staging",
    "read_manifest",
    "resolve_bundle",
]

BUNDLE_FORMAT = 1
MANIFEST = "manifest.json"
PLY_FILE = "map.ply"
TRACKER_FILE = "tracker.npz"
MAPPER_FILE = "mapper.npz"
LATEST = "latest"
_STAGING = ".staging-"
_CHUNK = 1 << 20


class BundleError(DataError):
    """A map bundle that cannot be used. ``kind``: ``missing`` (no bundle there), ``metadata`` (its
    manifest is unreadable or made for another camera, depth unit, tracker mode or format) or
    ``data`` (a file missing, truncated or changed): Nav2's LoadMap result codes follow it."""

    def __init__(self, message: str, kind: str = "data") -> None:
        super().__init__(message)
        self.kind = kind


@dataclass(frozen=True)
class Manifest:
    """A bundle's ``manifest.json``. camera: width, height, fx, fy, cx, cy, dist; depth_scale:
    16-bit depth units per metre the map was made with; files: name -> {bytes, sha256}."""

    format_version: int
    camera: dict[str, Any]
    tracker_mode: str
    depth_scale: float
    sh_degree: int
    map_frame: str
    frames: int
    keyframes: int
    gaussians: int
    source: str
    created: str
    files: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def bytes(self) -> int:
        return sum(int(f["bytes"]) for f in self.files.values())


def _digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def new_staging(root: str | os.PathLike[str]) -> Path:
    """A fresh hidden staging folder under ``root`` for one save; older ones (saves that died) go."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    for old in root.glob(f"{_STAGING}*"):
        pid = old.name[len(_STAGING):].split("-")[0]
        if pid.isdigit() and int(pid) != os.getpid() and not Path(f"/proc/{pid}").exists():
            shutil.rmtree(old, ignore_errors=True)
    staging = root / f"{_STAGING}{os.getpid()}-{secrets.token_hex(4)}"
    staging.mkdir()
    return staging


def commit_bundle(staging: Path, manifest: Manifest, name: str | None = None) -> Path:
    """Hash the staged files into ``manifest``, write it last, rename the folder to a new bundle
    name under its root and point ``latest`` at it. Returns the bundle's path."""
    files = {p.name: {"bytes": p.stat().st_size, "sha256": _digest(p)}
             for p in sorted(staging.iterdir()) if p.is_file() and p.name != MANIFEST}
    for need in (PLY_FILE, TRACKER_FILE, MAPPER_FILE):
        if need not in files:
            raise BundleError(f"cannot save a bundle without {need}")
    full = Manifest(**{**asdict(manifest), "format_version": BUNDLE_FORMAT, "files": files})
    atomic_write(staging / MANIFEST, lambda f: f.write((json.dumps(asdict(full), indent=2) + "\n").encode()))
    _fsync_dir(staging)
    root = staging.parent
    base = name or "map-" + dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    final, n = root / base, 1
    while final.exists() or final.is_symlink():
        n += 1
        final = root / f"{base}-{n}"
    os.rename(staging, final)  # never over an existing bundle: the name was free
    link = root / f".{LATEST}.{secrets.token_hex(4)}"
    os.symlink(final.name, link)
    os.replace(link, root / LATEST)
    _fsync_dir(root)
    return final


def resolve_bundle(path: str | os.PathLike[str]) -> Path:
    """The bundle folder ``path`` names: a bundle, ``latest``, or a folder holding ``latest``."""
    p = Path(path).expanduser()
    if not (p / MANIFEST).exists() and (p / LATEST).exists():
        p = p / LATEST
    p = p.resolve()
    if not p.is_dir():
        raise BundleError(f"map bundle {path}: no such folder", "missing")
    if p.name.startswith(_STAGING):
        raise BundleError(f"map bundle {path}: an unfinished save (staging folder), not a bundle", "missing")
    if not (p / MANIFEST).exists():
        raise BundleError(f"map bundle {path}: no {MANIFEST} (not a bundle, or a save that did not finish)",
                          "missing")
    return p


def read_manifest(bundle: Path) -> Manifest:
    try:
        raw = json.loads((bundle / MANIFEST).read_text())
    except (OSError, ValueError) as err:
        raise BundleError(f"map bundle {bundle}: {MANIFEST} is unreadable ({err})", "metadata") from err
    version = raw.get("format_version") if isinstance(raw, dict) else None
    if version != BUNDLE_FORMAT:
        raise BundleError(f"map bundle {bundle}: format_version {version!r}, this build reads {BUNDLE_FORMAT}",
                          "metadata")
    try:
        return Manifest(**raw)
    except TypeError as err:
        raise BundleError(f"map bundle {bundle}: {MANIFEST} fields: {err}", "metadata") from err


def _camera_mismatch(saved: dict[str, Any], camera: dict[str, Any]) -> str | None:
    for key in ("width", "height"):
        if int(saved[key]) != int(camera[key]):
            return f"camera.{key} {saved[key]} (this source: {camera[key]})"
    for key in ("fx", "fy", "cx", "cy"):
        if abs(float(saved[key]) - float(camera[key])) > 0.01 * max(abs(float(camera[key])), 1.0):
            return f"camera.{key} {float(saved[key]):.2f} (this source: {float(camera[key]):.2f})"
    return None


def check_bundle(path: str | os.PathLike[str], camera: dict[str, Any] | None = None,
                 depth_scale: float | None = None, tracker_mode: str | None = None,
                 verify_files: bool = True) -> tuple[Path, Manifest]:
    """(bundle folder, manifest) of ``path`` once it is usable here; BundleError, one line naming
    the field or file, when it was made with another camera, depth unit, tracker mode or format,
    or a file is missing, truncated or changed (``verify_files``: sizes and SHA-256)."""
    bundle = resolve_bundle(path)
    m = read_manifest(bundle)
    if camera is not None and (why := _camera_mismatch(m.camera, camera)):
        raise BundleError(f"map bundle {bundle} was made with another camera: {why}", "metadata")
    if depth_scale is not None and abs(m.depth_scale - depth_scale) > 1e-6 * depth_scale:
        raise BundleError(f"map bundle {bundle} has depth_scale {m.depth_scale:g} units per metre "
                          f"(this source: {depth_scale:g})", "metadata")
    if tracker_mode is not None and m.tracker_mode != tracker_mode:
        raise BundleError(f"map bundle {bundle} was made by a {m.tracker_mode} tracker (this run: {tracker_mode})",
                          "metadata")
    for need in (PLY_FILE, TRACKER_FILE, MAPPER_FILE):
        if need not in m.files:
            raise BundleError(f"map bundle {bundle}: the manifest lists no {need}", "metadata")
    if verify_files:
        for name, info in m.files.items():
            f = bundle / name
            if not f.is_file():
                raise BundleError(f"map bundle {bundle}: {name} is missing")
            if f.stat().st_size != int(info["bytes"]):
                raise BundleError(f"map bundle {bundle}: {name} is {f.stat().st_size} bytes, the manifest says "
                                  f"{info['bytes']} (truncated or replaced)")
            if _digest(f) != info["sha256"]:
                raise BundleError(f"map bundle {bundle}: {name} does not match its SHA-256 (corrupt or changed)")
    return bundle, m


def discard_staging(staging: Path) -> None:
    """A save that failed: its staging folder goes (the bundles stay as they were)."""
    with contextlib.suppress(OSError):
        shutil.rmtree(staging)
