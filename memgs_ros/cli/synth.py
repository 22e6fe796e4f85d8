"""``memgs synth``: generate the synthetic RGB-D room sequence as a TUM folder and/or a ROS 2 bag."""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = "generate a synthetic RGB-D sequence (exact depth and poses) as a TUM folder and/or a bag"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--spec", default="synthetic:w=640,h=480,n=120",
                   help="synthetic spec 'synthetic:key=value,...'; keys: w h n fps seed noise (depth std, m) "
                        "holes (fraction) amp rot aa (default: %(default)s)")
    p.add_argument("--out", type=Path, default=None, help="write a TUM RGB-D folder here (must not exist)")
    p.add_argument("--bag", type=Path, default=None,
                   help="write a ROS 2 bag here: .mcap or .db3 file, or a bag directory (must not exist)")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default=None,
                   help="bag storage (default: from the --bag suffix, else mcap)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    import time
    from collections.abc import Iterator

    from tqdm import tqdm

    from memgs_ros.core.geometry.frame import Frame
    from memgs_ros.errors import ConfigError
    from memgs_ros.io.bag_writer import write_bag
    from memgs_ros.io.synthetic import generate_frames, parse_spec, write_tum_folder
    from memgs_ros.io.synthetic_scene import build_scene

    if args.out is None and args.bag is None:
        raise ConfigError("nothing to write: give --out DIR and/or --bag PATH")
    spec = parse_spec(args.spec)
    t0 = time.perf_counter()
    scene = build_scene(spec.seed)
    print(f"{spec.to_string()}: scene built in {time.perf_counter() - t0:.2f} s")
    render_s = [0.0]

    def frames(desc: str) -> Iterator[Frame]:
        # rendering is deterministic, so each output renders afresh: memory stays at one frame
        gen = generate_frames(spec, scene)
        for _ in tqdm(range(spec.total_frames), desc=desc, unit="frame", disable=args.no_progress):
            t = time.perf_counter()
            f = next(gen)
            render_s[0] += time.perf_counter() - t
            yield f

    if args.out is not None:
        render_s[0] = 0.0
        t1 = time.perf_counter()
        n = write_tum_folder(frames("tum folder"), args.out)
        size = sum(p.stat().st_size for p in Path(args.out).rglob("*") if p.is_file())
        print(f"TUM folder {args.out}: {n} frames {spec.width}x{spec.height}, {size / 1e6:.1f} MB, "
              f"{time.perf_counter() - t1:.2f} s (rendering {render_s[0]:.2f} s, "
              f"{n / max(render_s[0], 1e-9):.1f} frames/s)")
    if args.bag is not None:
        render_s[0] = 0.0
        t2 = time.perf_counter()
        res = write_bag(frames("bag"), args.bag, storage=args.storage)
        print(f"bag {res.path}: {res.frames} frames {spec.width}x{spec.height}, {res.bytes / 1e6:.1f} MB, "
              f"{time.perf_counter() - t2:.2f} s (rendering {render_s[0]:.2f} s, "
              f"{res.frames / max(render_s[0], 1e-9):.1f} frames/s)")
    return 0
