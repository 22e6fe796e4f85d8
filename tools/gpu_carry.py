"""Prepare what a GPU machine without ROS needs for benchmarks/harness/bench_gpu.py, in one folder.

The lent GPU machines run another Python (3.12) and have no ROS, rosbags or gsplat, and reach
no package index. This writes, into a git-ignored folder that the run carries along:

  wheels/   cp312 manylinux wheels of what this machine has installed for rclpy, the messages,
            Fast DDS, rosbags, mcap and pytest (versions pinned to the ones tested here; the two
            sdist-only pure-Python dependencies built into wheels), plus gsplat 1.5.3 and its
            small dependencies. About 65 MB with the ROS wheels, 8 MB without (``--no-ros``).
  tum/      every ``--stride``-th of the first ``--frames`` frames of a TUM folder (rgb.txt,
            depth.txt, the images, the whole groundtruth.txt).

    python tools/gpu_carry.py gpu_carry --frames 120 --stride 2 [--no-ros]

then, on the GPU machine (carry ``gpu_carry``):

    python benchmarks/harness/bench_gpu.py --tum gpu_carry/tum/<name> --wheels gpu_carry/wheels

The carried paths may total 64 MiB a call, and what a call installs or copies to /tmp stays
while the machine is warm (30 s between calls). The 2026-11-26 H200 figures came from calls
back to back: (1) the ROS wheels, installed; (2) gsplat's wheel and the head's first 95 frames
with rgb.txt/depth.txt/groundtruth.txt, copied to a scratch folder HEAD outside the checkout and
gsplat built; (3) the other 105 frames into HEAD, then ``python3 benchmarks/harness/bench_gpu.py
--tum HEAD/<name>`` from the checkout's root (the script finds the package there without an
install).
"""
from __future__ import annotations

import argparse
import importlib.metadata as md
import re
import shutil
import subprocess
import sys
from pathlib import Path

from packaging.requirements import Requirement

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))  # benchmarks/ (not a package): _common
from _common import TUM_HELP, tum_path_or_exit  # noqa: E402

ROS_ROOTS = ("ros-jazzy-rclpy", "ros-jazzy-common-interfaces", "ros-jazzy-rmw-fastrtps-cpp", "rosbags", "mcap")
TEST_ROOTS = ("pytest",)
# gsplat's PyPI wheel is pure Python (it compiles its CUDA code at first use) and needs these.
GSPLAT = ("gsplat==1.5.3", "jaxtyping", "wadler-lindig", "rich", "markdown-it-py", "mdurl", "ninja")
PRESENT_THERE = {"numpy", "setuptools", "packaging", "torch"}  # on the GPU image already
PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64", "manylinux_2_5_x86_64",
             "linux_x86_64", "any")


def _key(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def closure(roots: tuple[str, ...]) -> dict[str, str]:
    """{name: installed version} of ``roots`` and everything they require, as installed here."""
    seen: dict[str, str] = {}
    stack = list(roots)
    while stack:
        name = stack.pop()
        if _key(name) in seen:
            continue
        try:
            dist = md.distribution(name)
        except md.PackageNotFoundError:
            raise SystemExit(f"gpu_carry: {name} is not installed here (pip install -e '.[ros,test]' first)")
        seen[_key(name)] = dist.version
        for r in dist.requires or []:
            req = Requirement(r)
            if req.marker is None or req.marker.evaluate({"extra": ""}):
                stack.append(req.name)
    return {k: v for k, v in seen.items() if k not in PRESENT_THERE}


def download(pins: list[str], dest: Path) -> None:
    cmd = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:", "--python-version",
           "3.12", "--implementation", "cp", "-d", str(dest)]
    for plat in PLATFORMS:
        cmd += ["--platform", plat]
    subprocess.run(cmd + pins, check=True)


def wheels(dest: Path, ros: bool) -> None:
    dest.mkdir(parents=True, exist_ok=True)
    pins = closure(TEST_ROOTS + (ROS_ROOTS if ros else ()))
    # No wheels are published for these two (pure Python): build them here.
    sdist_only = {k: v for k, v in pins.items() if k in ("empy", "lark-parser")}
    binary = [f"{k}=={v}" for k, v in pins.items() if k not in sdist_only]
    download(binary + list(GSPLAT), dest)
    if sdist_only:
        subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(dest),
                        *(f"{k}=={v}" for k, v in sdist_only.items())], check=True)


def tum_subset(src: Path, dest: Path, frames: int, stride: int) -> Path:
    """Every ``stride``-th of the first ``frames`` rgb/depth pairs (by line of rgb.txt/depth.txt)."""
    out = dest / f"{src.name}_{frames}s{stride}"
    if out.exists():
        shutil.rmtree(out)
    (out / "rgb").mkdir(parents=True)
    (out / "depth").mkdir()
    for listing in ("rgb.txt", "depth.txt"):
        lines = (src / listing).read_text().splitlines()
        header = [ln for ln in lines if ln.startswith("#")]
        data = [ln for ln in lines if ln.strip() and not ln.startswith("#")][:frames:stride]
        (out / listing).write_text("\n".join(header + data) + "\n")
        for ln in data:
            rel = ln.split()[1]
            shutil.copy2(src / rel, out / rel)
    for extra in ("groundtruth.txt", "camera.json", "accelerometer.txt"):
        if (src / extra).exists():
            shutil.copy2(src / extra, out / extra)
    return out


def _mb(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 2**20


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dest", type=Path, help="folder to write (keep it git-ignored)")
    ap.add_argument("--tum", type=Path, default=None, help=TUM_HELP)
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--stride", type=int, default=2)
    ap.add_argument("--no-ros", action="store_true", help="leave the ROS wheels out (~57 MB)")
    ap.add_argument("--no-data", action="store_true")
    args = ap.parse_args(argv)
    tum = None if args.no_data else tum_path_or_exit(ap, args.tum)
    wheels(args.dest / "wheels", ros=not args.no_ros)
    print(f"wheels: {_mb(args.dest / 'wheels'):.1f} MB")
    if not args.no_data:
        sub = tum_subset(tum, args.dest / "tum", args.frames, args.stride)
        print(f"{sub}: {_mb(sub):.1f} MB")
    print(f"total {_mb(args.dest):.1f} MB (a run may carry 64 MiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
